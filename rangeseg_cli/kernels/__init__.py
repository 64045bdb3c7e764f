"""Compiled (numba) kernels, the choice of backend, their cache and the threads."""
