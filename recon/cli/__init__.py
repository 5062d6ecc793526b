"""The `recon` command line: click commands that parse flags and call a stage (no math here)."""
