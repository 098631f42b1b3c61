"""Readers and writers for the files artists and engines open: one module per format."""
