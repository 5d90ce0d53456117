"""simulation (placeholder public API; filled in by its issue)."""
