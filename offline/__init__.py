"""Offline learning: subject templates for the service, and the data-driven shoulder skeleton.

May import ``labeler_service`` (I/O, kernels, template schema); never the reverse.
"""
