"""The ``equibim`` command. Thin: parses arguments with tyro and calls library functions."""

from __future__ import annotations

import dataclasses
import time
from typing import Annotated, Union

from pathlib import Path

import tyro

from equibim_jax.experiments.demo import DemoConfig
from equibim_jax.experiments.pipeline import EnvSpec, ModelOptions


@dataclasses.dataclass
class SymmetryDemo:
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


def _command_line(argv: list[str] | None) -> str:
    import shlex
    import sys

    return "equibim " + " ".join(shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))


@dataclasses.dataclass
class Demo:
    """The main experiment: baseline vs +EquiBim, demos from one side, evaluated on both.

    Generates expert demos, trains two diffusion policies that differ only in L_sym,
    evaluates both in closed loop on the trained and the mirrored side, prints the table,
    and writes results/demo.json and results/demo.png.
    """

    config: Annotated[DemoConfig, tyro.conf.arg(name="")] = dataclasses.field(default_factory=DemoConfig)

    def run(self, argv=None) -> None:
        from equibim_jax.experiments.demo import format_table, run_demo

        res = run_demo(self.config, command=_command_line(argv))
        out = Path(self.config.out_dir)
        t = res["timings"]
        print(f"\n{res['task']}: {res['demos']['episodes']} expert demos on the {res['trained_side']} "
              f"side, {self.config.train_steps} training steps per policy, "
              f"{self.config.eval_episodes} closed-loop episodes per side\n")
        print(format_table(res))
        eq = [f"{n}: {res[n]['train']['final']['equiv_err']:.3f}" for n in ("baseline", "equibim")]
        print(f"\nrelative equivariance error of the noise prediction at the end: {', '.join(eq)}")
        sq = [f"{n}: {res[n]['open_loop_error']['equivariance']['arm_rad']:.4f} rad "
              f"(gripper {res[n]['open_loop_error']['equivariance']['gripper']:.3f})" for n in ("baseline", "equibim")]
        print(f"equivariance error of the sampled actions, |S pi(S O, S z) - pi(O, z)| on the demo "
              f"windows: {', '.join(sq)}")
        print(f"wall time {res['wall_time_s']:.0f} s (generate {t['generate_s']:.0f} s, train "
              f"{t['train_baseline_s']:.0f} + {t['train_equibim_s']:.0f} s, eval {t['eval_s']:.0f} s; "
              f"compile included)")
        print(f"wrote {out / 'demo.json'} and {out / 'demo.png'}")


@dataclasses.dataclass
class Generate:
    """Roll out a task's scripted expert in batched MJX and save the successful episodes (zarr)."""

    out: str
    """Dataset path to write (a .zarr directory)."""
    env: EnvSpec = dataclasses.field(default_factory=EnvSpec)
    n_episodes: int = 24
    """Successful episodes to keep."""
    seed: int = 0
    overwrite: bool = False
    """Replace an existing dataset at --out."""

    def run(self, argv=None) -> None:
        from equibim_jax.experiments.pipeline import generate_dataset

        demos, stats = generate_dataset(self.env, self.out, self.n_episodes, seed=self.seed,
                                        overwrite=self.overwrite)
        print(f"wrote {self.out}: {demos.n_episodes} episodes, {int(demos.length.sum())} steps; "
              f"expert success {stats['successes']}/{stats['attempts']} in {stats['wall_s']:.1f} s")


@dataclasses.dataclass
class Train:
    """Train a diffusion policy (sym_weight > 0 adds L_sym); resumes from --out if it holds a checkpoint."""

    data: str
    """Dataset written by `equibim generate`."""
    out: str
    """Run folder: ckpt/ and train.jsonl."""
    model: ModelOptions = dataclasses.field(default_factory=ModelOptions)
    sym_weight: float = 0.1
    """lambda of L_sym (0 = plain behaviour cloning)."""
    sym_stop_gradient: bool = False
    """Treat S(pi(O)) in L_sym as a fixed target: only the mirrored prediction is pulled."""
    sym_norm: str = "l2"
    """L_sym as the paper's unsquared per-sample norm (l2) or the squared error (mse)."""
    sym_space: str = "eps"
    """Compare the noise predictions (eps) or the clean actions they imply (x0) in L_sym."""
    sym_warmup_steps: int = 0
    """Ramp lambda linearly from 0 over this many steps (0: constant)."""
    sym_start_step: int = 0
    """L_sym's weight is 0 before this step (BC first), then as --sym-warmup-steps says."""
    sym_batch_size: int | None = None
    """Samples per step that also go through the mirrored branch for L_sym (default: the
    whole batch). 32 of 64 takes 29 ms a step against 38 ms for all 64 (BC alone: 21 ms)."""
    mirror_augment: bool = False
    """Also fit the mirrored demos by BC (mirror data augmentation, a baseline to EquiBim)."""
    steps: int = 1000
    batch_size: int = 64
    learning_rate: float = 3e-3
    warmup_steps: int = 50
    steps_per_dispatch: int = 50
    checkpoint_every: int | None = None
    """Steps between checkpoints (default: at the end only)."""
    seed: int = 0

    def run(self, argv=None) -> None:
        from equibim_jax.experiments.pipeline import train_policy
        from equibim_jax.training import TrainConfig

        tc = TrainConfig(batch_size=self.batch_size, learning_rate=self.learning_rate,
                         total_steps=self.steps, warmup_steps=min(self.warmup_steps, self.steps),
                         steps_per_dispatch=self.steps_per_dispatch, sym_weight=self.sym_weight,
                         sym_stop_gradient=self.sym_stop_gradient, sym_norm=self.sym_norm, sym_space=self.sym_space,
                         sym_warmup_steps=min(self.sym_warmup_steps, self.steps),
                         sym_start_step=self.sym_start_step,
                         sym_batch_size=self.sym_batch_size,
                         mirror_augment=self.mirror_augment, seed=self.seed)
        s = train_policy(self.data, self.out, self.model, tc, checkpoint_every=self.checkpoint_every)
        f = s["final"]
        print(f"trained to step {s['steps']} in {s['train_s']:.1f} s: bc {f.get('bc', float('nan')):.4f}, "
              f"sym {f.get('sym', float('nan')):.4f}, equivariance error {f.get('equiv_err', float('nan')):.4f}; "
              f"checkpoint {s['checkpoint']}, log {s['log']}")


@dataclasses.dataclass
class Eval:
    """Closed-loop success of a trained policy on its trained side and the mirrored side."""

    run_dir: tyro.conf.Positional[str]
    """Run folder written by `equibim train`."""
    episodes: int = 64
    """Episodes per side."""
    seed: int = 1
    mirror_noise: bool = False
    """Pair the sides in all their randomness: the mirrored episode also samples with the
    mirrored DDIM noise. Then also reports how far each mirrored trajectory, mapped back
    by S, drifts from its trained-side twin (0 for an exactly equivariant policy)."""
    out: str | None = None
    """Also write the results as JSON here."""

    def run(self, argv=None) -> None:
        from equibim_jax._io import atomic_write_json
        from equibim_jax.experiments.pipeline import evaluate_checkpoint, load_policy

        if self.mirror_noise:
            import jax

            from equibim_jax.evaluation.rollout import mirror_pair_gap

            model, state, normalizer, config = load_policy(self.run_dir)
            res = mirror_pair_gap(config["env_spec"].make(), model, normalizer, state.ema_params,
                                  jax.random.key(self.seed), self.episodes, progress=True)
        else:
            res = evaluate_checkpoint(self.run_dir, self.episodes, seed=self.seed)
        for side in ("trained", "mirrored"):
            r = res[side]
            lo, hi = r["ci95"]
            print(f"{side:<9} success {r['success']:.3f}  95% CI [{lo:.3f}, {hi:.3f}]  "
                  f"({r['successes']}/{r['episodes']})")
        if self.mirror_noise:
            print(f"pairs: {res['both']} succeed on both sides, {res['trained_only']} on the trained side "
                  f"only, {res['mirrored_only']} on the mirrored side only, {res['neither']} on neither")
            print("median over pairs of max_j |S(q_mirrored(t)) - q_trained(t)|_j at step t: "
                  + ", ".join(f"t={t}: {g:.4f}" for t, g in res["gap_median_at"].items()))
        if self.out:
            atomic_write_json(self.out, {**res, "command": _command_line(argv)})


@dataclasses.dataclass
class Equivariance:
    """How equivariant trained policies are, on demo windows: the noise prediction and the sampled actions."""

    run_dirs: tyro.conf.Positional[tuple[str, ...]]
    """Run folders written by `equibim train` (or `equibim demo`'s demo/baseline, demo/equibim)."""
    data: str
    """Dataset whose windows (and their mirror images) are used."""
    windows: int = 128
    seed: int = 0
    out: str | None = None
    """Also write the results as JSON here."""

    def run(self, argv=None) -> None:
        from equibim_jax._io import atomic_write_json
        from equibim_jax.data.dataset import load
        from equibim_jax.experiments.pipeline import load_policy, open_loop_errors

        demos = load(self.data)
        res = {}
        for run_dir in self.run_dirs:
            model, state, normalizer, config = load_policy(run_dir)
            env = config["env_spec"].make()
            ol = open_loop_errors(model, normalizer, {"p": state.ema_params}, demos, env,
                                  n_windows=self.windows, seed=self.seed)["p"]
            res[run_dir] = ol
            eq = ol["equivariance"]
            print(f"{run_dir}: sampled actions |S pi(S O, S z) - pi(O, z)|: arm {eq['arm_rad']:.4f} rad, "
                  f"gripper {eq['gripper']:.3f}; action error on demos {ol['demos']['arm_rad']:.4f} rad, "
                  f"on mirrored demos {ol['mirrored_demos']['arm_rad']:.4f} rad")
            print("  gap per action dim (normalised rms): "
                  + " ".join(f"{x:.3f}" for x in eq["per_dim_normalized_rms"]))
        if self.out:
            atomic_write_json(self.out, {**res, "command": _command_line(argv)})


Command = Union[
    Annotated[Demo, tyro.conf.subcommand("demo")],
    Annotated[Generate, tyro.conf.subcommand("generate")],
    Annotated[Train, tyro.conf.subcommand("train")],
    Annotated[Eval, tyro.conf.subcommand("eval")],
    Annotated[Equivariance, tyro.conf.subcommand("equivariance")],
    Annotated[SymmetryDemo, tyro.conf.subcommand("symmetry")],
    Annotated[Robots, tyro.conf.subcommand("robots")],
]


def main(argv: list[str] | None = None) -> None:
    cmd = tyro.cli(Command, args=argv)
    if isinstance(cmd, (Demo, Generate, Train, Eval, Equivariance)):
        cmd.run(argv)
    else:
        cmd.run()


if __name__ == "__main__":
    main()
