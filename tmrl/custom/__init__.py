"""Compatibility package mirroring the original tmrl layout; holds no logic of its own."""
