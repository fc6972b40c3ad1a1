"""The core: networks and their CasADi graphs, closed loops and Lie derivatives, the graph
walker, simulation, the rounding model, domains, grids and samples, JSON input,
provenance, determinism, the errors and the optional dependencies (the bottom layer; it
imports no other layer of the project).
"""
