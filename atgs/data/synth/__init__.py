"""The built-in synthetic scenes: their content (``scene``: cameras, textured meshes, analytic
motion, exact ground truth), a GL mesh renderer of them (``mesh_renderer``), and the N3DV-layout
videos it writes plus the cached default scene (``videos``)."""
