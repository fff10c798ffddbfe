"""Searches over the physics and the operators: inverse kinematics (:mod:`tdcr.search.inverse`) and
design search (:mod:`tdcr.search.design`)."""
