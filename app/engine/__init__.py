"""The live engine behind the GUI (no Qt here).

- sources.py: where frames come from (the rig, simulated or real, or a recorded session replayed
  through drivers/replay.py);
- live_rig.py: the engine (LiveRig): its capture and reconstruction threads, and what it publishes;
- recording.py: a recording's flow samples, events, the subject's calibration and the values after
  each manoeuvre (SubjectRecording);
- cycle_buffer.py: a head's newest light cycles and dark frames, between capture and reconstruction;
- head_stream.py: a head's live maps, made as `photopft process` makes them;
- flow_display.py: the flow sensor's volume as the live view draws it;
- feeds.py: what it shows (Snapshot, HeadView) and knows of its source (EngineInfo);
- flow_record.py: the recording's flow samples for the feedback after each manoeuvre;
- process.py: the engine in a process of its own (EngineProcess);
- protocol.py: LiveEngine, the calls both engines answer.
"""
