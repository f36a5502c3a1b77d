"""Offline stages that turn meshes into packaged models: one module per stage."""
