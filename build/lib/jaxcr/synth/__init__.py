"""Synthetic scene generator: independent ray-casting renderer, textures, occluders, model error, presets."""
