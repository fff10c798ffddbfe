"""Neural operators of the TDCR equilibrium map (PyTorch).  Layers -> models -> training -> export."""
