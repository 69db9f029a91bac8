"""Where and how a network's forward pass runs: the torch or onnxruntime backend, its numeric
precision, ONNX export and onnxruntime sessions, and the memory a freed network leaves."""
