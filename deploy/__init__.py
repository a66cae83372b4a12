"""Deployment files; ``deploy.local`` holds the local helper scripts, importable as modules."""
