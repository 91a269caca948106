"""What every stage may import: shared geometry and atomic file writes; it imports no stage."""
