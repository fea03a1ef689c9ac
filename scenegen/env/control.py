"""robosuite's default arm controller, the same torques at a fraction of the Python.

robosuite recomputes its controller at every physics substep (25 per control step here) through a
chain of properties and name lookups: the action's dimension checked three times (each a
concatenation of the parts' limits), every site looked up by name, its Jacobian allocated and
computed once for the position, again for the rotation and twice more for the velocities, the
gripper's joint state and mass matrix recomputed for a command that only changes with the action.
Measured on a labelled scene, that was about twice the physics it drives (issue 44, docs/env.md).

:class:`LeanControl` computes the same torques for the configuration this project uses, the BASIC
composite controller (OSC_POSE arm: delta input in the base frame, fixed impedance, decoupled
position and orientation, no interpolator; the Panda's gripper through robosuite's simple grip
controller): the same reads of the simulator, the same numpy expressions in the same order and
robosuite's own compiled kernels (``opspace_matrices``, ``orientation_error``, ``nullspace_torques``),
so the torques are bit-identical (tests/env/test_control.py steps both side by side). Goals are
still set by robosuite's own ``set_goal``, once per action; the gripper's command, a function of the
action alone, is computed then and held for the substeps. What it leaves out: robosuite's
proprioceptive history buffers (``robot.recent_qpos``, ``recent_ee_*``), which nothing here reads.

:func:`lean_control` returns None for any other configuration (another controller, an interpolator,
a second arm): the environment then keeps robosuite's own path.
"""

from __future__ import annotations

import mujoco
import numpy as np


def lean_control(robot) -> LeanControl | None:
    """A :class:`LeanControl` for ``robot`` (a robosuite robot after its environment's reset), or
    None when its controllers are not the configuration it reproduces."""
    from robosuite.controllers.parts.arm.osc import OperationalSpaceController
    from robosuite.controllers.parts.gripper.simple_grip import SimpleGripController

    controllers = robot.composite_controller.part_controllers
    if set(controllers) != {"right", "right_gripper"} or robot.arms != ["right"]:
        return None
    arm, grip = controllers["right"], controllers["right_gripper"]
    if not (
        type(arm) is OperationalSpaceController
        and type(grip) is SimpleGripController
        and arm.input_type == "delta"
        and arm.input_ref_frame == "base"
        and arm.impedance_mode == "fixed"
        and arm.uncoupling
        and arm.interpolator_pos is None
        and arm.interpolator_ori is None
        and grip.interpolator is None
        and arm.num_ref_sites == 1
        and arm.lite_physics
        and arm.position_limits is None
    ):
        return None
    return LeanControl(robot, arm, grip)


def _indexer(index) -> slice | list[int]:
    """A slice for a run of consecutive indices (a view, no gather), else the list."""
    index = [int(i) for i in index]
    if index == list(range(index[0], index[0] + len(index))):
        return slice(index[0], index[0] + len(index))
    return index


class LeanControl:
    """One robot's torques per physics substep: :meth:`control` replaces robosuite's
    ``robot.control(action, policy_step)``."""

    def __init__(self, robot, arm, grip):
        from robosuite.utils.control_utils import nullspace_torques, opspace_matrices, orientation_error

        self._opspace, self._orientation_error, self._nullspace = (
            opspace_matrices,
            orientation_error,
            nullspace_torques,
        )
        self.robot, self.arm, self.grip = robot, arm, grip
        sim = robot.sim
        self.model, self.data = sim.model._model, sim.data._data
        nv = self.model.nv
        self.ref_site = sim.model.site_name2id(arm.ref_name)
        self.center_site = sim.model.site_name2id(f"{arm.naming_prefix}{arm.part_name}_center")
        self.qpos_index, self.qvel_index = _indexer(arm.qpos_index), _indexer(arm.qvel_index)
        self.qvel_list = list(arm.qvel_index)
        # fixed impedance: the gains never change
        self.kp_pos, self.kp_ori = np.array(arm.kp[0:3]), np.array(arm.kp[3:6])
        self.kd_pos, self.kd_ori = arm.kd[0:3], arm.kd[3:6]
        self.jacp, self.jacr = np.zeros((3, nv)), np.zeros((3, nv))
        self.center_jacp, self.center_jacr = np.zeros((3, nv)), np.zeros((3, nv))
        self.full_mass = np.ndarray(shape=(nv, nv), dtype=np.float64, order="C")
        arm_actuators = robot._ref_actuators_indexes_dict["right"]
        grip_actuators = robot._ref_actuators_indexes_dict[robot.get_gripper_name("right")]
        ctrlrange = self.model.actuator_ctrlrange
        self.arm_actuators, self.grip_actuators = arm_actuators, grip_actuators
        self.arm_low, self.arm_high = ctrlrange[arm_actuators, 0], ctrlrange[arm_actuators, 1]
        self.grip_low, self.grip_high = ctrlrange[grip_actuators, 0], ctrlrange[grip_actuators, 1]
        self.grip_ctrl: np.ndarray | None = None

    def control(self, action, policy_step: bool) -> None:
        """robosuite's ``robot.control`` for this configuration: the arm's state read once, the goal
        set by robosuite on a policy step, the torques written to ``data.ctrl``."""
        arm, data = self.arm, self.data
        # composite_controller.update_state: the controller's origin, the arm's base
        arm.origin_pos = np.array(data.site_xpos[self.center_site])
        arm.origin_ori = np.array(data.site_xmat[self.center_site].reshape([3, 3]))
        # robosuite reads the state only when its flag says so: after a reset the flag is clear
        # (the state read at the reset's forced update, before the scene's fingers and objects were
        # placed, drives the first substep), after every substep it is set
        if arm.new_update:
            self._read_arm_state()
        if policy_step:
            self.robot.composite_controller.set_goal(action)  # arm: no second read (new_update cleared)
            self.grip_ctrl = np.clip(self.grip.run_controller(), self.grip_low, self.grip_high)
        torques = self._arm_torques()
        arm.new_update = True  # what robosuite's run_controller leaves behind
        data.ctrl[self.arm_actuators] = np.clip(torques, self.arm_low, self.arm_high)
        data.ctrl[self.grip_actuators] = self.grip_ctrl

    def _read_arm_state(self) -> None:
        """robosuite's ``Controller.update`` (lite physics: no forward) for one reference site."""
        arm, model, data = self.arm, self.model, self.data
        jacp, jacr = self.jacp, self.jacr
        mujoco.mj_jacSite(model, data, jacp, jacr, self.ref_site)
        arm.ref_pos[:] = np.array(data.site_xpos[self.ref_site])
        arm.ref_ori_mat[:, :] = np.array(data.site_xmat[self.ref_site].reshape([3, 3]))
        arm.ref_pos_vel[:] = np.dot(jacp, data.qvel)
        arm.ref_ori_vel[:] = np.dot(jacr, data.qvel)
        arm.J_pos[:, :] = jacp[:, self.qvel_index]
        arm.J_ori[:, :] = jacr[:, self.qvel_index]
        arm.J_full[:3] = arm.J_pos
        arm.J_full[3:] = arm.J_ori
        arm.joint_pos = np.array(data.qpos[self.qpos_index])
        arm.joint_vel = np.array(data.qvel[self.qvel_index])
        mujoco.mj_fullM(model, self.full_mass, data.qM)
        # robosuite's gather, whose result is Fortran-ordered: the compiled kernels below are
        # specialised by memory layout, and a C-ordered copy changes their last bits
        arm.mass_matrix = self.full_mass[self.qvel_list, :][:, self.qvel_list]
        arm.new_update = False

    def _arm_torques(self) -> np.ndarray:
        """robosuite's ``OperationalSpaceController.run_controller`` after its update, for delta
        input in the base frame, fixed impedance, decoupled, no interpolator."""
        arm, data = self.arm, self.data
        desired_world_pos = arm.origin_pos + np.dot(arm.origin_ori, arm.goal_pos)
        desired_world_ori = np.dot(arm.origin_ori, arm.goal_ori)
        ori_error = self._orientation_error(desired_world_ori, arm.ref_ori_mat)
        position_error = desired_world_pos - arm.ref_pos
        mujoco.mj_jacSite(self.model, data, self.center_jacp, self.center_jacr, self.center_site)
        base_pos_vel = np.dot(self.center_jacp, data.qvel)
        vel_pos_error = -(arm.ref_pos_vel - base_pos_vel)
        desired_force = np.multiply(position_error, self.kp_pos) + np.multiply(vel_pos_error, self.kd_pos)
        base_ori_vel = np.dot(self.center_jacr, data.qvel)
        vel_ori_error = -(arm.ref_ori_vel - base_ori_vel)
        desired_torque = np.multiply(ori_error, self.kp_ori) + np.multiply(vel_ori_error, self.kd_ori)
        _, lambda_pos, lambda_ori, nullspace_matrix = self._opspace(
            arm.mass_matrix, arm.J_full, arm.J_pos, arm.J_ori
        )
        decoupled_wrench = np.concatenate(
            [np.dot(lambda_pos, desired_force), np.dot(lambda_ori, desired_torque)]
        )
        torques = np.dot(arm.J_full.T, decoupled_wrench) + data.qfrc_bias[self.qvel_index]
        torques += self._nullspace(
            arm.mass_matrix, nullspace_matrix, arm.initial_joint, arm.joint_pos, arm.joint_vel
        )
        arm.torques = torques
        return torques
