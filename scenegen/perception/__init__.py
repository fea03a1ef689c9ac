"""Seeing: what the robot perceives at a decision point.

``observation.observe`` renders the decision point's RGB-D frames and turns them into a
:class:`~scenegen.perception.observation.TargetView` (the target's points and the other objects');
``points`` back-projects masked depth into world points and summarises them; ``robot_state`` reads
the robot's own state (proprioception).
"""
