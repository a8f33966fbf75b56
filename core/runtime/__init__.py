"""Plumbing every stage uses: atomic writes, the resume rule, progress, worker threads, settings files."""
