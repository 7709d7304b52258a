"""The live engine behind the GUI (no Qt here).

- sources.py: where frames come from (the rig, simulated or real, or a recorded session replayed
  through drivers/replay.py);
- live_rig.py: the engine (LiveRig): capture, recording and reconstruction threads;
- feeds.py: what it shows (Snapshot, HeadView) and knows of its source (EngineInfo);
- flow_record.py: the recording's flow samples for the feedback after each manoeuvre;
- process.py: the engine in a process of its own (EngineProcess);
- protocol.py: LiveEngine, the calls both engines answer.
"""
