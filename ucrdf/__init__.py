"""U(C)RDF: the Unified (Continuum) Robot Description Format information model."""
