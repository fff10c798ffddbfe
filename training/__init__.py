"""tdcr-surrogates: physics, design space, data and (with torch) the neural operators.

Importing this package, ``training.physics`` or ``training.design_space`` never imports torch.
"""
