"""Command-line applications, one module per ``fgjax`` command: each parses its arguments, calls the library and
prints. No application imports another."""
