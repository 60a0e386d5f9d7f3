"""GLSL splatting shaders, shipped as package data; read with importlib.resources.files("atgs.shaders")."""
