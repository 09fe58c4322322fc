"""Command line and experiments of the wavy-water testbed."""
