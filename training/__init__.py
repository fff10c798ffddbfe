"""Offline work of tdcr-surrogates (depends on ``tdcr``, never on ``service``): solver datasets
(``training.dataset``, no torch) and, with torch, the neural operators (``training.operators``).
"""
