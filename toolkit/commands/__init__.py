"""Small subcommands of the ``projo4d`` CLI (one module each)."""
