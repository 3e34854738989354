"""The command line (``rtfem``), the demo, the benchmark tables and the pictures."""
