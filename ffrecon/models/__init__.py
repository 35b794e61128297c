"""Feed-forward models: the ONNX runner and one adapter per model family.

Decoding and alignment are functions of plain arrays, separate from the ONNX session, so they can
be tested on exact inputs; the runner only moves arrays in and out of onnxruntime.
"""
