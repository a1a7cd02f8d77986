"""The benchmark (``make bench``): ``python -m condtrack_cli.evaluate.bench``; see ``__main__.py``."""
