"""tdcr-surrogates: physics, design space, data and (with torch) the neural operators.

Importing this package, ``tdcr.physics`` or ``tdcr.design_space`` never imports torch.
"""
