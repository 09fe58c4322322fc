"""Rendering: ocean waves become meshes in Mitsuba 3 scenes of the paper's two optical systems."""
