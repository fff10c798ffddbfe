"""The robot: batches of designs and loads (:mod:`tdcr.robot.designs`) and the design space --
Table I, the admissible bounds and the feature layout (:mod:`tdcr.robot.design_space`)."""
