"""Parallel and distributed work: the Dask client helper and load-balanced verification.
"""
