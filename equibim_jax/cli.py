"""The ``equibim`` command. Thin: tyro parses the library's config dataclasses, and each
subcommand calls library functions.

``equibim COMMAND --help`` lists every flag of a command. Configs: ``--config FILE`` (a
``config.json`` of a run, or a file in ``tasks/``) sets the defaults that flags then
override.
"""

import dataclasses
import shlex
import sys
import time
from typing import Any, Literal

import tyro

from equibim_jax._sharding import maybe_initialize_distributed, maybe_use_cpu_cores
from equibim_jax.config import ConfigError, EvalConfig, TaskConfig, config_from_dict, find_config, load_config

COMMANDS = ("demo", "generate", "experts", "pictures", "train", "eval", "equivariance", "symmetry", "robots", "tasks",
            "policies", "export", "import", "experiment")


def _command_line(argv: list[str]) -> str:
    return "equibim " + " ".join(shlex.quote(a) for a in argv)


def _pop_option(args: list[str], flag: str) -> tuple[str | None, list[str]]:
    """Remove ``flag VALUE`` (or ``flag=VALUE``) from ``args``; returns (VALUE, rest)."""
    rest, value, i = [], None, 0
    while i < len(args):
        a = args[i]
        if a == flag and i + 1 < len(args):
            value, i = args[i + 1], i + 2
            continue
        if a.startswith(flag + "="):
            value, i = a.split("=", 1)[1], i + 1
            continue
        rest.append(a)
        i += 1
    return value, rest


@dataclasses.dataclass
class Generate:
    """Roll out a task's scripted expert in batched MJX and save the successful episodes (zarr);
    with the `asymmetric_quality` shift the perturbed (bad) episodes are kept too."""

    task: str
    """Task name (`equibim tasks` lists them)."""
    out: str
    """Dataset path to write (a .zarr directory)."""
    episodes: int = 50
    """Successful episodes to keep (50 per task, as in the paper)."""
    options: dict[str, str] = dataclasses.field(default_factory=dict)
    """Task options as KEY VALUE pairs, e.g. `--options side left n_points 64`."""
    seed: int = 0
    overwrite: bool = False
    """Replace an existing dataset at --out."""

    def run(self) -> None:
        from equibim_jax.data.generate import generate_dataset
        from equibim_jax.tasks import make_env

        env = make_env(self.task, **self.options)
        demos, stats = generate_dataset(env, self.out, self.episodes, seed=self.seed, overwrite=self.overwrite)
        print(f"wrote {self.out}: {demos.n_episodes} episodes, {demos.n_steps} steps; expert success "
              f"{stats['successes']}/{stats['attempts']} in {stats['wall_s']:.1f} s")


def _train_command(policy_default: Any, train_default: Any):
    from equibim_jax.training.train_step import TrainConfig

    @dataclasses.dataclass
    class Train:
        """Train a policy on a dataset (train.sym_weight > 0 adds L_sym); resumes from --out
        if it holds a checkpoint. --policy NAME picks the policy (`equibim policies`);
        --config RUN/config.json repeats a run's policy and train settings."""

        data: str
        """Dataset written by `equibim generate`."""
        out: str
        """Run folder: config.json, train.jsonl, ckpt/."""
        policy: Any = policy_default
        train: TrainConfig = train_default
        steps: int | None = None
        """Shorthand for --train.total-steps."""
        checkpoint_every: int | None = None
        """Steps between checkpoints (default: at the end only)."""
        symmetry: str | None = None
        """Mirror map JSON (`equibim symmetry --out`) giving S for a dataset without a simulated env
        (`equibim import`); checked against the dataset's names, sizes and cameras."""

        def run(self) -> None:
            from equibim_jax.interop.mapping import InteropError
            from equibim_jax.interop.symmetry import training_env
            from equibim_jax.training.run import train

            tc = self.train if self.steps is None else dataclasses.replace(self.train, total_steps=self.steps)
            try:  # S from a mirror map for data without a simulated env (docs/data.md)
                env = training_env(self.data, self.symmetry)
            except InteropError as e:
                raise ConfigError(str(e)) from None
            s = train(self.data, self.out, self.policy, tc, env=env, checkpoint_every=self.checkpoint_every)
            f = s["final"]
            print(f"trained to step {s['steps']} in {s['train_s']:.1f} s: bc {f.get('bc', float('nan')):.4f}, "
                  f"sym {f.get('sym', float('nan')):.4f}, equivariance error {f.get('equiv_err', float('nan')):.4f}; "
                  f"config {s['config']}, checkpoint {s['checkpoint']}, log {s['log']}")

    Train.__annotations__["policy"] = type(policy_default)
    return Train


def _online_train_command(policy_default: Any, train_default: Any):
    from equibim_jax.training.online import OnlineConfig
    from equibim_jax.training.train_step import TrainConfig

    @dataclasses.dataclass
    class OnlineTrain:
        """Train a policy from fresh expert demonstrations streamed into an on-device ring
        buffer: envs, buffer and update in one compiled loop, no dataset on disk. --policy
        NAME picks the policy; rerunning resumes the parameters from --out."""

        task: str
        """A registered task (`equibim tasks`)."""
        out: str
        """Run folder: config.json, train.jsonl, ckpt/."""
        policy: Any = policy_default
        train: TrainConfig = train_default
        online: OnlineConfig = dataclasses.field(default_factory=OnlineConfig)
        options: tuple[str, ...] = ()
        """Task options as option=value (e.g. side=left); obs defaults to the policy's fields."""
        steps: int | None = None
        """Shorthand for --train.total-steps (train.steps-per-dispatch is set to online.iterations x
        online.grad-steps)."""
        checkpoint_every: int | None = None
        """Steps between checkpoints (default: at the end only)."""

        def run(self) -> None:
            from equibim_jax.evaluation.experts import parse_task_spec
            from equibim_jax.training.online import train_online

            spec = self.task + (":" + ",".join(self.options) if self.options else "")
            name, opts = parse_task_spec(spec)
            per = self.online.iterations * self.online.grad_steps  # steps of one dispatch
            tc = dataclasses.replace(self.train, total_steps=self.steps or self.train.total_steps,
                                     steps_per_dispatch=per)
            s = train_online(TaskConfig(name, opts), self.out, self.policy, tc, self.online,
                             checkpoint_every=self.checkpoint_every)
            f = s["final"]
            rate = (f"{s['env_steps_per_s']:.0f} env-steps/s with {s['train_steps_per_s']:.2f} train-steps/s"
                    if s["env_steps_per_s"] is not None else "one dispatch only (no rate apart from compile)")
            print(f"trained to step {s['steps']} on {s['episodes']} fresh expert episodes "
                  f"({s['successes']} kept) in {s['train_s']:.1f} s ({rate}); bc {f.get('bc', float('nan')):.4f}, "
                  f"sym {f.get('sym', float('nan')):.4f}; config {s['config']}, checkpoint {s['checkpoint']}")

    OnlineTrain.__annotations__["policy"] = type(policy_default)
    return OnlineTrain


@dataclasses.dataclass
class Eval:
    """Closed-loop success of a trained run on its training distribution and on the mirror
    image of each initial state."""

    run_dir: tyro.conf.Positional[str]
    """Run folder written by `equibim train`."""
    eval: EvalConfig = dataclasses.field(default_factory=EvalConfig)
    episodes: int | None = None
    """Shorthand for --eval.episodes."""
    out: str | None = None
    """Also write the results as JSON here."""
    out_dir: str | None = None
    """Write eval.json, episodes.jsonl (one record per episode and side) and videos/ here."""
    videos: int = 0
    """Film the first N episodes, each beside its mirrored twin (default folder: RUN/eval/videos)."""
    video_episodes: tuple[int, ...] = ()
    """Film these episodes instead (indices below the episode count), e.g. `--video-episodes 0 3`."""
    video_format: Literal["gif", "mp4"] = "gif"
    """gif (Pillow) or mp4 (PyAV, `pip install av`)."""
    video_size: int = 128
    """Frame side of each half of a video, in pixels."""
    video_fps: int = 20
    video_every: int = 1
    """Keep every N-th control step in the videos."""
    equivariance_demos: int = 0
    """If > 0, also measure the equivariance error on windows of this many fresh expert demos."""

    def run(self, command: str) -> None:
        from equibim_jax._io import atomic_write_json
        from equibim_jax.evaluation.evaluate import evaluate_run

        cfg = self.eval if self.episodes is None else dataclasses.replace(self.eval, episodes=self.episodes)
        if self.videos and self.video_episodes:
            raise SystemExit("equibim eval: give --videos N or --video-episodes I J ..., not both")
        if self.videos < 0:
            raise SystemExit(f"equibim eval: --videos must be >= 0, got {self.videos}")
        if self.videos > cfg.episodes:
            raise SystemExit(f"equibim eval: --videos {self.videos} is more than the {cfg.episodes} episodes "
                             f"evaluated")
        chosen = tuple(range(self.videos)) or self.video_episodes
        try:  # the checks evaluate_run makes, made here first to exit with a message
            from equibim_jax.evaluation.videos import check_episodes

            check_episodes(chosen, cfg.episodes)
            if self.video_size < 8 or self.video_fps < 1 or self.video_every < 1 or self.equivariance_demos < 0:
                raise ValueError("--video-size must be >= 8, --video-fps and --video-every >= 1, "
                                 "--equivariance-demos >= 0")
            if chosen and self.video_format == "mp4":
                if self.video_size % 2:
                    raise ValueError(f"mp4 needs an even --video-size, got {self.video_size}")
                import av  # noqa: F401
        except ValueError as e:
            raise SystemExit(f"equibim eval: {e}") from None
        except ImportError:
            raise SystemExit("equibim eval: mp4 videos need PyAV (pip install av); "
                             "or use --video-format gif") from None
        res = evaluate_run(self.run_dir, cfg, out_dir=self.out_dir, video_episodes=chosen,
                           video_size=self.video_size, video_format=self.video_format,
                           video_fps=self.video_fps, video_every=self.video_every,
                           equivariance_demos=self.equivariance_demos)
        for side in ("trained", "mirrored"):
            r = res[side]
            lo, hi = r["ci95"]
            nan = f", {r['nan_actions']} NaN actions in {r['episodes_with_nan']} episodes" if r.get("nan_actions") else ""
            print(f"{side:<9} success {r['success']:.3f}  95% CI [{lo:.3f}, {hi:.3f}]  "
                  f"({r['successes']}/{r['episodes']}{nan})")
        if cfg.mirror_noise:
            print(f"pairs: {res['both']} succeed on both sides, {res['trained_only']} on the trained side "
                  f"only, {res['mirrored_only']} on the mirrored side only, {res['neither']} on neither")
            print("median over pairs of max_j |S(q_mirrored(t)) - q_trained(t)|_j at step t: "
                  + ", ".join(f"t={t}: {g:.4f}" for t, g in res["gap_median_at"].items()))
        if "equivariance" in res:
            eq = res["equivariance"]
            from equibim_jax.evaluation.open_loop import describe_errors

            print(f"equivariance on {eq['windows']} windows of {eq['demos']} fresh expert demos: relative "
                  f"{eq['relative']:.4f}; sampled actions |S pi(S O, S z) - pi(O, z)|: "
                  f"{describe_errors(eq['equivariance'])}; action error on the demos: "
                  f"{describe_errors(eq['demos_error'])}, on their mirror images: "
                  f"{describe_errors(eq['mirrored_demos_error'])}")
        for v in res.get("videos", []):
            print(f"video of episode {v['episode']}: {v['path']} ({v['frames']} frames, "
                  f"{v['width']}x{v['height']})")
        if self.out_dir:
            print(f"wrote {self.out_dir}/eval.json and {self.out_dir}/episodes.jsonl")
        if self.out:
            atomic_write_json(self.out, {**res, "command": command})


@dataclasses.dataclass
class Equivariance:
    """How equivariant trained runs are on demo windows: the sampled actions and their errors."""

    run_dirs: tyro.conf.Positional[tuple[str, ...]]
    """Run folders written by `equibim train` (or `equibim demo`'s demo/baseline, demo/equibim)."""
    data: str
    """Dataset whose windows (and their mirror images) are used."""
    windows: int = 128
    seed: int = 0
    out: str | None = None
    """Also write the results as JSON here."""

    def run(self, command: str) -> None:
        from equibim_jax._io import atomic_write_json
        from equibim_jax.data.dataset import load
        from equibim_jax.evaluation.open_loop import describe_errors, open_loop_errors
        from equibim_jax.training.run import load_run

        demos = load(self.data)
        res = {}
        for run_dir in self.run_dirs:
            run = load_run(run_dir)
            ol = open_loop_errors(run.policy, run.normalizer, {"p": run.state.ema_params}, demos,
                                  run.make_env(), n_windows=self.windows, seed=self.seed)["p"]
            res[run_dir] = ol
            eq = ol["equivariance"]
            print(f"{run_dir}: sampled actions |S pi(S O, S z) - pi(O, z)|: {describe_errors(eq)}; action "
                  f"error on demos {describe_errors(ol['demos'])}, on mirrored demos "
                  f"{describe_errors(ol['mirrored_demos'])}")
            print("  gap per action dim (normalised rms): "
                  + " ".join(f"{x:.3f}" for x in eq["per_dim_normalized_rms"]))
        if self.out:
            atomic_write_json(self.out, {**res, "command": command})


@dataclasses.dataclass
class SymmetryDemo:
    """Derive and verify the mirror S of a built-in robot or of any MJCF (--mjcf, --mirror-normal); print the
    joint map, residuals per body and the dynamic report; --out writes the mirror map as JSON. Exits with
    status 1 and the per-body report when the model is not symmetric within the tolerance."""

    robot: str = "robot_a"
    """Built-in robot name (see `equibim robots`); not used with --mjcf."""
    mjcf: str | None = None
    """Path of any MJCF model to derive S for (instead of --robot); needs --mirror-normal."""
    mirror_normal: tuple[float, float, float] | None = None
    """Normal of the mirror plane, e.g. `1 0 0` for x = 0 (default with --robot: the robot's plane)."""
    mirror_point: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """A point on the mirror plane."""
    approximate: bool = False
    """Derive the best map of a nearly symmetric model and report its residual per body."""
    dynamics: Literal["report", "strict"] = "report"
    """report: measure asymmetric masses, centres of mass, inertias and geoms; strict: refuse them."""
    tol: float | None = None
    """Largest accepted forward-kinematics residual in m (default 0.0005; 0.05 with --approximate)."""
    out: str | None = None
    """Write the mirror map as JSON here."""
    n_verify: int = 256
    """Random joint configurations used to verify S on forward kinematics."""
    seed: int = 0

    def run(self) -> None:
        import warnings

        import mujoco

        from equibim_jax.symmetry import Mirror, SymmetryError, SymmetryWarning, derive_symmetry, save_mirror_map

        t0 = time.perf_counter()
        ee_sites = None
        if self.mjcf is not None:
            if self.mirror_normal is None:
                print("equibim symmetry: --mjcf needs --mirror-normal NX NY NZ (e.g. 1 0 0 for the plane x = 0)",
                      file=sys.stderr)
                raise SystemExit(2)
            try:
                model = mujoco.MjModel.from_xml_path(self.mjcf)
            except (ValueError, FileNotFoundError) as e:
                print(f"equibim symmetry: cannot load {self.mjcf}: {e}", file=sys.stderr)
                raise SystemExit(2) from None
            mirror, source = Mirror(self.mirror_normal, self.mirror_point), self.mjcf
        else:
            from equibim_jax.sim import load_robot, robot_info

            model, mirror = load_robot(self.robot)
            if self.mirror_normal is not None:
                mirror = Mirror(self.mirror_normal, self.mirror_point)
            ee_sites, source = tuple(robot_info(self.robot).ee_sites), f"robot {self.robot}"
        print(f"{source}: {model.nbody} bodies, {model.njnt} joints, {model.nu} actuators")
        print(f"mirror plane: normal {mirror.normal}, point {mirror.point}\n")
        # Concessions (intersected ranges) are printed with the report, not as Python warnings.
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", SymmetryWarning)
            try:
                ms = derive_symmetry(model, mirror, tol=self.tol, n_verify=self.n_verify, seed=self.seed,
                                     approximate=self.approximate, dynamics=self.dynamics)
            except SymmetryError as e:
                notes = "".join(f"\nwarning: {w.message}" for w in caught if issubclass(w.category, SymmetryWarning))
                print(f"equibim symmetry: {source} is not mirror-symmetric within the tolerance"
                      f"{'' if self.approximate else ' (try --approximate for a nearly symmetric robot)'}:\n{e}"
                      f"{notes}", file=sys.stderr)
                raise SystemExit(1) from None
        dt = time.perf_counter() - t0
        print(ms.describe())
        print("\nqpos map  (q' = P D q + b):")
        print(ms.qpos.describe())
        print(f"\n{ms.report(min_residual=1e-9)}")
        print(f"\nverified forward-kinematics residual over {self.n_verify} random postures: "
              f"{ms.residual:.3e} m  (derived and verified in {dt:.2f} s)")
        if self.out:
            save_mirror_map(ms, self.out, ee_sites=ee_sites)
            print(f"wrote {self.out}")


def _demo(args: list[str], command: str) -> None:
    from equibim_jax.experiments.demo import DEFAULT_CONFIG, DemoConfig, format_table, load_demo_config, run_demo

    path, args = _pop_option(args, "--config")
    default = load_demo_config(path or DEFAULT_CONFIG)
    cfg = tyro.cli(DemoConfig, args=args, default=default, prog="equibim demo",
                   description=f"The main experiment: baseline vs +EquiBim, evaluated on the training "
                               f"distribution and its mirror image. Settings from --config "
                               f"(default {DEFAULT_CONFIG}); flags override them.")
    res = run_demo(cfg, command=command)
    t = res["timings"]
    print(f"\n{res['task']} {res['task_options']}: {res['demos']['episodes']} expert demos, "
          f"{cfg.train.total_steps} training steps per policy, {cfg.eval.episodes} closed-loop episodes per side\n")
    print(format_table(res))
    eq = [f"{n}: {res[n]['train']['final']['equiv_err']:.3f}" for n in ("baseline", "equibim")]
    print(f"\nrelative equivariance error of the prediction L_sym compares, at the end: {', '.join(eq)}")
    sq = [f"{n}: {res[n]['open_loop_error']['equivariance']['arm_rad']:.4f} rad "
          f"(gripper {res[n]['open_loop_error']['equivariance']['gripper']:.3f})" for n in ("baseline", "equibim")]
    print(f"equivariance error of the sampled actions, |S pi(S O, S z) - pi(O, z)| on the demo windows: "
          f"{', '.join(sq)}")
    print(f"wall time {res['wall_time_s']:.0f} s (generate {t['generate_s']:.0f} s, train "
          f"{t['train_s']:.0f} s for both policies, eval {t['eval_s']:.0f} s; compile included)")
    print(f"wrote {cfg.out_dir}/demo.json, {cfg.out_dir}/demo.png and {cfg.out_dir}/demo/config.json")


def _train(args: list[str]) -> None:
    from equibim_jax.policies import policy_config_class
    from equibim_jax.training.train_step import TrainConfig

    path, args = _pop_option(args, "--config")
    name, args = _pop_option(args, "--policy")
    policy, train = None, TrainConfig()
    if path:
        data = load_config(find_config(path))
        try:
            from equibim_jax.policies import PolicyConfig

            policy = config_from_dict(PolicyConfig, data["policy"]) if "policy" in data else None
            train = config_from_dict(TrainConfig, data["train"]) if "train" in data else train
        except ConfigError as e:
            raise ConfigError(f"{path}: {e}") from None
    if name is not None and (policy is None or policy.name != name):
        policy = policy_config_class(name)()
    if policy is None:
        policy = policy_config_class("dp3")()
    online = "--online" in args
    if online:
        args = [a for a in args if a != "--online"]
        cmd = tyro.cli(_online_train_command(policy, train), args=args, prog="equibim train --online")
    else:
        cmd = tyro.cli(_train_command(policy, train), args=args, prog="equibim train")
    cmd.run()


@dataclasses.dataclass
class Experts:
    """Success rate of every task's scripted expert over seeded starts, with 95 % intervals.

    Writes `{task: {"success", "ci95", "episodes", ...}}` to --out after each task and
    skips the tasks --out already holds with the same settings (a rerun resumes)."""

    episodes: int = 200
    """Starts per task (keys `jax.random.split(jax.random.key(seed), episodes)`)."""
    out: str | None = None
    """JSON file to write (and resume from)."""
    tasks: tuple[str, ...] = ()
    """Tasks to run, each `task` or `task:option=value,...` (default: every registered task
    with an expert, then the robotwin_faithful=True variants)."""
    seed: int = 2024
    batch: int = 25
    """Episodes per compiled call."""

    def run(self) -> None:
        from equibim_jax.evaluation.experts import default_specs, expert_table, markdown_table, parse_task_spec
        from equibim_jax.tasks import make_scene, task_entry, task_options

        try:
            specs = self.tasks or tuple(default_specs())
            for spec in specs:
                task, opts = parse_task_spec(spec)
                if task_entry(task).expert is None:  # task_entry raises on unknown names
                    raise ValueError(f"task {task!r} has no scripted expert")
                bad = sorted(set(opts) - set(task_options(task)))
                if bad:
                    raise ValueError(f"unknown option(s) {bad} for task {task!r}; valid options: "
                                     f"{list(task_options(task))}")
                # bad values of the scene's options fail here, before any compile
                make_scene(task, **{k: v for k, v in opts.items() if k in task_entry(task).scene_fields})
            if self.episodes < 1:
                raise ValueError(f"--episodes must be >= 1, got {self.episodes}")
            results = expert_table(specs, self.out, self.episodes, self.seed, self.batch)
        except ConfigError:
            raise
        except ValueError as e:
            raise ConfigError(str(e)) from None
        print(markdown_table(results))
        if self.out:
            print(f"wrote {self.out}")


@dataclasses.dataclass
class Pictures:
    """Head-camera pictures of every task's expert: a grid of first and last frames of an
    episode and of its mirror image (OUT/tasks.png, or OUT/GRID), and one GIF per task
    (OUT/gifs/)."""

    out: str = "docs"
    """Folder for tasks.png and gifs/."""
    tasks: tuple[str, ...] = ()
    """Tasks to show (default: every registered task with an expert)."""
    seed: int = 0
    size: int = 128
    """Frame side in pixels."""
    cache: str = "results/pictures_cache"
    """Folder keeping each task's frames, so an interrupted run resumes."""
    grid: str = "tasks.png"
    """File name of the frame grid in --out (a .png name)."""

    def run(self) -> None:
        from equibim_jax.evaluation.pictures import make_pictures
        from equibim_jax.tasks import task_entry, task_names

        try:
            tasks = self.tasks or tuple(n for n in task_names() if task_entry(n).expert is not None)
            for t in tasks:
                if task_entry(t).expert is None:
                    raise ValueError(f"task {t!r} has no scripted expert")
            if self.size < 16:
                raise ValueError(f"--size must be at least 16 pixels, got {self.size}")
            if not self.grid.endswith(".png") or "/" in self.grid or self.grid == ".png":
                raise ValueError(f"--grid must be a file name ending in .png, got {self.grid!r}")
        except ValueError as e:
            raise ConfigError(str(e)) from None
        summary = make_pictures(tasks, self.out, self.seed, self.size, self.cache, grid=self.grid)
        for t, s in summary.items():
            print(f"{t}: episode {'success' if s['success'] else 'FAILURE'}, mirrored "
                  f"{'success' if s['mirror_success'] else 'FAILURE'}; {s['gif']} ({s['gif_bytes'] / 1e3:.0f} kB)")
        print(f"wrote {self.out}/{self.grid}")


def _usage() -> str:
    return ("usage: equibim COMMAND [--help] [flags]\n\ncommands:\n"
            "  demo          the main experiment (settings from tasks/place_empty_cup.json)\n"
            "  experiment    run or resume a paper table (tasks/experiments/NAME.json)\n"
            "  generate      scripted-expert demos of a task into a dataset\n"
            "  experts       success rates of the tasks' scripted experts (JSON, resumable)\n"
            "  pictures      task pictures: a frame grid (tasks.png) and one GIF per task\n"
            "  train         train a policy on a dataset (with L_sym)\n"
            "  eval          closed-loop success on both sides of a trained run\n"
            "  equivariance  open-loop equivariance and action errors of trained runs\n"
            "  symmetry      derive and verify the mirror S of a robot\n"
            "  export        write a dataset as DP3 zarr or LeRobot v3 (docs/data.md)\n"
            "  import        read a DP3 zarr or LeRobot v3 dataset into ours (docs/data.md)\n"
            "  robots        list the shipped robots\n"
            "  tasks         list the registered tasks and their options\n"
            "  policies      list the registered policies\n")


def main(argv: list[str] | None = None) -> None:
    # First, before any JAX backend starts: one CPU device per core, so that batches are
    # split over the cores (EQUIBIM_JAX_CPU_DEVICES=off keeps one), and join a
    # multi-process run if the environment asks for one (EQUIBIM_JAX_DISTRIBUTED=1 or
    # JAX_COORDINATOR_ADDRESS); docs/scaling.md.
    try:
        maybe_use_cpu_cores()
    except ValueError as e:
        print(f"equibim: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    maybe_initialize_distributed()
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return
    cmd, args = argv[0], argv[1:]
    command = _command_line(argv)
    try:
        if cmd == "demo":
            _demo(args, command)
        elif cmd == "experiment":
            from equibim_jax.experiments.runner import cli_main

            cli_main(args, command)
        elif cmd == "train":
            _train(args)
        elif cmd == "generate":
            tyro.cli(Generate, args=args, prog="equibim generate").run()
        elif cmd == "experts":
            tyro.cli(Experts, args=args, prog="equibim experts").run()
        elif cmd == "pictures":
            tyro.cli(Pictures, args=args, prog="equibim pictures").run()
        elif cmd == "eval":
            tyro.cli(Eval, args=args, prog="equibim eval").run(command)
        elif cmd == "equivariance":
            tyro.cli(Equivariance, args=args, prog="equibim equivariance").run(command)
        elif cmd in ("export", "import"):
            from equibim_jax.interop.cli import Export, Import

            tyro.cli(Export if cmd == "export" else Import, args=args, prog=f"equibim {cmd}").run()
        elif cmd == "symmetry":
            tyro.cli(SymmetryDemo, args=args, prog="equibim symmetry").run()
        elif cmd == "robots":
            from equibim_jax.sim import robot_names

            print("\n".join(robot_names()))
        elif cmd == "tasks":
            from equibim_jax.tasks import task_entry, task_names

            for n in task_names():
                e = task_entry(n)
                print(f"{n}: robot {e.robot}, step limit {e.step_limit}, options {list(e.scene_fields)}")
        elif cmd == "policies":
            from equibim_jax.policies import policy_config_class, policy_names

            for n in policy_names():
                print(f"{n}: {policy_config_class(n).__name__}")
        else:
            print(f"equibim: unknown command {cmd!r}\n\n{_usage()}", file=sys.stderr)
            raise SystemExit(2)
    except ConfigError as e:
        print(f"equibim {cmd}: {e}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
