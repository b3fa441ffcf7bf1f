"""Compatibility package mirroring the original ``tmrl.custom.tm.utils``; no logic of its own."""
