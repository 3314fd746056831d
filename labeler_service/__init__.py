"""Online labeling of optical motion-capture markers for multiple interacting performers.

Online half of the project: capture I/O, scenes, the labeler (seed 003) and the streaming
service. The offline package (``offline``) may import from here; never the reverse.
"""

__version__ = "0.1.0"
