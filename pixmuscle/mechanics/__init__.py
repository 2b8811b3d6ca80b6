"""Mechanics of the pixel-point model: materials, integration, assembly, boundary conditions, solver.

Units: cm, N, N/cm². Import the modules directly, e.g. ``from pixmuscle.mechanics import materials``.
"""
