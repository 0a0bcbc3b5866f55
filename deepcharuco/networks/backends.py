"""The names of the ways the networks can run (`deepcharuco.networks.runtime` runs them): here, apart, so that command
lines can offer the choice without loading PyTorch."""

BACKENDS = ("auto", "torch", "onnx", "onnx-int8")
