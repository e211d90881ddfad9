"""Measuring tools: ``crowd-bench`` and what it runs. Never imported by the runtime (``crowd/``, ``app/``)."""
