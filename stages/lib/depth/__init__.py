"""Depth of a background photo: the sidecar formats, the monocular models (ONNX, transformers) and the
recovery of scale and holes."""
