"""Kinematic model plugins (PCC, PPC, …), found by name and through entry points."""
