"""From frames to height maps: a light cycle's signal, normals, depth and distance (the session's
orchestration is core/pipeline/process.py)."""
