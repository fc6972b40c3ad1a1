"""The certificate kernel: the one definition of conditions (a), (b), (c) of a region of
attraction, the level search, and compositional certificates of interconnected systems.
"""
