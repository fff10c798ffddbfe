"""HTTP inference service and the torch-free ONNX runtime it uses."""
