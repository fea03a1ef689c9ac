"""Acting: the retrieve task (``task``: success measured by the simulator), motions through the
controller (``motion``), grasp primitives with planners and executors (``primitives``), and one
primitive observed, planned and executed (``rollout.run_primitive``)."""
