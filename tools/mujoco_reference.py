"""Golden numbers for procl's physics tests, computed with the real MuJoCo (pip install mujoco).

Not part of the test suite (procl needs no Python); run by hand to regenerate the pinned values
in src/envs/point_mass.rs and src/envs/reacher.rs:  python3 tools/mujoco_reference.py
"""
import mujoco
import numpy as np

POINT_MASS = """
<mujoco>
  <option timestep="0.02" integrator="Euler" gravity="0 0 -9.81"/>
  <default>
    <joint type="slide" limited="true" range="-.29 .29" damping="1"/>
    <motor gear=".1" ctrlrange="-1 1" ctrllimited="true"/>
  </default>
  <worldbody>
    <body name="pointmass" pos="0 0 .01">
      <joint name="root_x" axis="1 0 0"/>
      <joint name="root_y" axis="0 1 0"/>
      <geom name="pointmass" type="sphere" size=".01" mass=".3" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <actuator>
    <motor name="tx" joint="root_x"/>
    <motor name="ty" joint="root_y"/>
  </actuator>
</mujoco>
"""

REACHER = """
<mujoco>
  <option timestep="0.02" integrator="Euler" gravity="0 0 0"/>
  <default>
    <joint type="hinge" axis="0 0 1" damping="0.01" limited="true"/>
    <motor gear=".05" ctrlrange="-1 1" ctrllimited="true"/>
  </default>
  <worldbody>
    <body name="arm" pos="0 0 .01">
      <joint name="shoulder" range="-160 160"/>
      <geom name="arm" type="capsule" fromto="0 0 0 0.12 0 0" size=".01" contype="0" conaffinity="0"/>
      <body name="hand" pos=".12 0 0">
        <joint name="wrist" range="0 160"/>
        <geom name="hand" type="capsule" fromto="0 0 0 0.1 0 0" size=".01" contype="0" conaffinity="0"/>
        <body name="finger" pos=".12 0 0">
          <geom name="finger" type="sphere" size=".01" contype="0" conaffinity="0"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="shoulder" joint="shoulder"/>
    <motor name="wrist" joint="wrist"/>
  </actuator>
</mujoco>
"""


def rollout(xml, q0, qd0, controls):
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qpos[:] = q0
    d.qvel[:] = qd0
    out = []
    for u in controls:
        d.ctrl[:] = u
        mujoco.mj_step(m, d)
        out.append((d.qpos.copy(), d.qvel.copy()))
    return m, d, out


def main():
    np.set_printoptions(precision=12)
    print("mujoco", mujoco.__version__)
    # Step response from rest, u = (1, 0).
    _, _, traj = rollout(POINT_MASS, [0, 0], [0, 0], [[1, 0]] * 50)
    for k in (1, 5, 10, 25, 50):
        print(f"point_mass step t={k*0.02:.2f} x={traj[k-1][0][0]:.12f} v={traj[k-1][1][0]:.12f}")
    # Driven into the +x wall and the -y wall, then released.
    controls = [[1, -1]] * 150 + [[0, 0]] * 50
    _, _, traj = rollout(POINT_MASS, [0.2, -0.1], [0, 0], controls)
    for k in (20, 40, 60, 100, 150, 151, 160, 200):
        q, qd = traj[k - 1]
        print(f"point_mass wall k={k} q={q.tolist()} qd={qd.tolist()}")
    # Reacher mass matrix at q = 0.
    m, d, _ = rollout(REACHER, [0, 0], [0, 0], [])
    mujoco.mj_forward(m, d)
    M = np.zeros((2, 2))
    try:
        mujoco.mj_fullM(m, d, M)  # MuJoCo >= 3.4 signature
    except TypeError:
        mujoco.mj_fullM(m, M, d.qM)
    print("reacher M(q=0)", M.tolist())
    print("reacher dof_invweight0", m.dof_invweight0.tolist())
    # Reacher: free swing with coupling, then driven into both limits.
    controls = [[1, -1]] * 100 + [[-1, 1]] * 100 + [[0.3, 0.7]] * 100
    _, _, traj = rollout(REACHER, [0.5, 1.0], [0, 0], controls)
    for k in (1, 10, 50, 100, 150, 200, 250, 300):
        q, qd = traj[k - 1]
        print(f"reacher k={k} q={q.tolist()} qd={qd.tolist()}")


if __name__ == "__main__":
    main()
