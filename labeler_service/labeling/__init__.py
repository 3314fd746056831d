"""The labeling core: frame types, templates, training, the online labeler, the closest-point
baseline and the numba kernels. No sockets, no asyncio."""
