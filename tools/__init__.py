"""Host-side tools: the ucr CLI dispatcher, the emulated segment chain, flashing, VM helpers."""
