"""The ``equibim`` command. Thin: parses arguments with tyro and calls library functions."""

from __future__ import annotations

import dataclasses
import time
from typing import Annotated, Union

import tyro


@dataclasses.dataclass
class Demo:
    """Derive the mirror S of a robot from its MJCF and print the joint map and its residual."""

    robot: str = "robot_a"
    """Robot name (see `equibim robots`)."""
    n_verify: int = 256
    """Random joint configurations used to verify S on forward kinematics."""
    seed: int = 0

    def run(self) -> None:
        from equibim_jax.sim import load_robot
        from equibim_jax.symmetry import derive_symmetry, verify_symmetry

        t0 = time.perf_counter()
        model, mirror = load_robot(self.robot)
        ms = derive_symmetry(model, mirror)
        res = verify_symmetry(model, ms, n=self.n_verify, seed=self.seed)
        dt = time.perf_counter() - t0
        print(f"robot {self.robot}: {model.nbody} bodies, {model.njnt} joints, {model.nu} actuators")
        print(f"mirror plane: normal {mirror.normal}, point {mirror.point}\n")
        print(ms.describe())
        print("\nqpos map  (q' = P D q + b):")
        print(ms.qpos.describe())
        print(f"\nverified forward-kinematics residual over {self.n_verify} random postures: "
              f"{res:.3e} m  (derived and verified in {dt:.2f} s)")


@dataclasses.dataclass
class Robots:
    """List the shipped robots."""

    def run(self) -> None:
        from equibim_jax.sim import robot_names

        for n in robot_names():
            print(n)


Command = Union[
    Annotated[Demo, tyro.conf.subcommand("demo")],
    Annotated[Robots, tyro.conf.subcommand("robots")],
]


def main(argv: list[str] | None = None) -> None:
    cmd = tyro.cli(Command, args=argv)
    cmd.run()


if __name__ == "__main__":
    main()
