"""Scenes: contact hybrid systems built from constraints."""
