"""The verbs of the `photopft` command line, one module each (app/cli.py registers them)."""
