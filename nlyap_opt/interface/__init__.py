"""The ``nlyap`` command line: the commands, their argument types and exit codes (the top
layer; it may import every other layer).
"""
