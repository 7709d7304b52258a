"""From frames to height maps: a light cycle's signal, normals, depth, distance, and `process`."""
