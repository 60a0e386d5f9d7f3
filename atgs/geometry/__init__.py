"""Rig geometry: what the cameras see, prove empty, cover and reach, each written once.

- projection: points -> pixel coordinates, depth, and the one test "in front of the camera and
  inside its image" (``near`` a parameter);
- rays: rays through pixel positions (the inverse of the pinhole), and back to world points;
- free_space: the space the measured points prove empty, per position (nearest-depth grids);
- ray_free_space: the space each training camera sees through, per ray (measured depths);
- seen_space: the space the cameras see, from the cameras alone (layout depth ranges, samples
  in the intersection of frusta, a pointless scene's start points);
- clearance: the balls around the training cameras' housings where no Gaussian may sit;
- reach: which anchors' Gaussians can reach a view (measured reach spheres against frusta);
- coverage: how much of each image the points explain, and by how many cameras;
- rig_check: the sparse-rig warning.

Nothing here reads prepared data or knows the model or the trainer: data preparation, the
model and training all build on it (tests/test_model_boundaries.py).
"""
