"""Learned dynamics of an unknown system: the network φ and its training, the configuration
and the stage with its η gate, the error models and their sound bounds (Lipschitz
constants, interval suprema), and the inner set proved from data.
"""
