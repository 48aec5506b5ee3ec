"""Pytest configuration: its presence puts ``tests/`` on ``sys.path`` (rootdir import mode),
so test modules can ``from support import ...``."""
