"""The neural operators at run time, torch-free: the ONNX runtime (:mod:`tdcr.surrogates.runtime`),
their calibrated error bounds and tolerances (:mod:`tdcr.surrogates.bounds`) and the engine that
answers a validated request with them (:mod:`tdcr.surrogates.engine`)."""
