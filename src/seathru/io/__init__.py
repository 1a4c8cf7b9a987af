"""File input/output. Everything that touches the disk lives here or in ``seathru.steps``."""
