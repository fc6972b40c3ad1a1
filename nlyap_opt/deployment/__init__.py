"""A certificate put to use: re-verified runs and closed-loop simulation, C99 and ONNX
export, and the CLF-QP safety filter.
"""
