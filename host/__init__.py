"""Host daemon for a chain of continuum robot segments (runs on a Raspberry Pi)."""
