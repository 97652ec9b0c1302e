"""End-to-end experiments built from the library's pieces."""
