"""The live 3D view of the twin robot (viser): the scene, its live/replay feed, and its API route."""
