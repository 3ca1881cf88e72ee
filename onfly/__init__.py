"""onfly."""
