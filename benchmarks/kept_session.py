"""A subject's session kept beside its bench row without its frames: what `bench population --reread`
reads (the rig, the events, the flow sensor's samples, the truth, the frames' times and ids), in a few
MB where the session as rendered is 1.5 GB at scale 0.25 and about four times that at 0.5. A run at the
larger scales, which spans days and more renders than a disk keeps, can then be read again by the
analysis of one commit after its renders are gone."""

from __future__ import annotations

import os
from pathlib import Path

import h5py

# the root attribute that marks such a copy, and says why its frames read as zeros
FRAMES_NOT_KEPT = "frames_not_kept"


def keep_without_frames(session: Path, into: Path) -> None:
    """Writes `into` (a temporary name renamed when complete): `session` whole but for each head's
    frames, left as an unwritten dataset of their shape and type (no bytes on disk, zeros if read)."""
    partial = into.with_name(into.name + ".part")
    with h5py.File(session, "r") as source, h5py.File(partial, "w") as copy:
        copy.attrs.update(source.attrs)
        copy.attrs[FRAMES_NOT_KEPT] = f"a bench's copy of {session.name} for reading its results again"
        for name, item in source.items():
            if name != "heads":
                source.copy(item, copy, name)
                continue
            heads = copy.create_group("heads")
            heads.attrs.update(item.attrs)
            for head, group in item.items():
                kept = heads.create_group(head)
                kept.attrs.update(group.attrs)
                for key, dataset in group.items():
                    if key != "frames":
                        group.copy(dataset, kept, key)
                        continue
                    frames = kept.create_dataset("frames", shape=dataset.shape, dtype=dataset.dtype,
                                                 chunks=(1,) + dataset.shape[1:] if dataset.shape[0] else None)
                    frames.attrs.update(dataset.attrs)
    os.replace(partial, into)

