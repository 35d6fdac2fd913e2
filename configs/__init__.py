"""The ready configurations, installed as the package ``workflows.configs`` (see setup.py)."""
