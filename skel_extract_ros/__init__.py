"""Template-free articulated skeleton extraction from single depth camera sequences."""

__version__ = '0.1.0'
