"""Input/output: run folders and logs, field output (XDMF), particle output, probes, checkpoints."""
