"""The training stages and :func:`train_stage`, which runs one of them into ``RUN/<stage>/``.

A run directory holds one sub-directory per stage::

    RUN_DIR/vae/       checkpoints/, model.safetensors + model.json (EMA weights), metrics.json
    RUN_DIR/teacher/   checkpoints/, latents/ (the run's latent cache, every stage), model.safetensors + model.json
    RUN_DIR/tf|ode|dmd|long|steps/  the causal student's stages (world_model.train.student_stages)
    RUN_DIR/shallow/   the finished student in fewer blocks (world_model.train.shallow_stage)
    RUN_DIR/reference/ the reference-conditioned model (world_model.train.reference_stage)
    RUN_DIR/first_frame/  the one-step first-frame model (world_model.train.first_frame_stage)
    RUN_DIR/rollout_decoder/  the decoder fine-tuned on the student's rollouts (world_model.train.rollout_decoder_stage)
    RUN_DIR/range_head/  the VAE's range head, trained on the student's rollouts (world_model.train.range_head_stage)
    RUN_DIR/camera_decoder/  the cameras' own decoder, on the rollouts (world_model.train.camera_decoder_stage)
    RUN_DIR/lora/CASE/ one LoRA adapter per long-tail case (world_model.train.lora_stage)

Each stage reads the exports of the stages before it. Rerunning a command resumes from the stage's
latest checkpoint; a finished stage rerun with a larger ``steps`` continues training.

Each stage owns an options type (:attr:`Stage.options`): :class:`StageOptions` (the config and the
schedule), which the student stages extend with their student config
(:class:`~world_model.train.student_stages.StudentStageOptions`) and the ``lora`` stage with the
adapter's settings (:class:`~world_model.train.lora_stage.LoraStageOptions`);
:func:`stage_options` picks a stage's from a whole chain's settings, as the command line does.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

from world_model.data.clips import write_json_atomic
from world_model.model.config import ModelConfig, get_preset, without_label_decoder
from world_model.precision import check_dtype, dit_precision, resolve_bf16
from world_model.train.camera_decoder_stage import camera_decoder_stage
from world_model.train.device import TrainPlace, resolve_device
from world_model.train.first_frame_stage import first_frame_stage
from world_model.train.lora_stage import LORA_STEPS, LoraStageOptions, lora_setup, lora_stage, lora_stage_dir
from world_model.train.range_head_stage import range_head_stage
from world_model.train.reference_stage import reference_stage
from world_model.train.rollout_decoder_stage import rollout_decoder_stage
from world_model.train.run import StageOptions, StageRun, StageRuntime
from world_model.train.shallow_stage import shallow_stage
from world_model.train.student_stages import StudentStageOptions, student_setup, student_stage
from world_model.train.teacher_stage import teacher_stage
from world_model.train.trainer import LoopOptions, TrainConfig
from world_model.train.vae_stage import check_decoder_config, decoder_stage, vae_stage


@dataclass(frozen=True)
class Stage:
    """One stage of the registry: how it trains, its defaults and the options type it owns.

    ``options``: the type :func:`train_stage` takes for it; ``setup`` turns its stage-specific
    fields into the keyword arguments of ``train`` and ``directory`` places the stage in the run
    (default ``RUN/<name>``). ``config_sections``: the config sections its weights depend on (None:
    the whole config; ``"teacher"``: :meth:`ModelConfig.teacher_settings`).
    """

    name: str
    train: Callable[..., dict]  # (StageRun, **setup(options)) -> summary
    batch_size: int  # CPU-sized defaults
    lr: float
    ckpt_every: int
    options: type[StageOptions] = StageOptions
    setup: Callable[[Any], dict] | None = None  # (options) -> keyword arguments of train
    directory: Callable[[Path, Any], Path] | None = None  # (RUN, options) -> the stage's directory
    config_sections: tuple[str, ...] | str | None = None
    # Default steps where a step costs far more than a teacher's: per preset, or one count for all.
    steps: dict[str, int] | int | None = None
    check: Callable[[ModelConfig], None] | None = None  # refuses a config before anything is written


def _student(kind: str, batch_size: int, lr: float, ckpt_every: int, steps: int) -> Stage:
    """A student stage: its options carry the student config."""
    return Stage(
        kind,
        partial(student_stage, kind),
        batch_size,
        lr,
        ckpt_every,
        StudentStageOptions,
        student_setup,
        steps={"default": steps},
    )


def _decoder(kind: str, train: Callable[[Any], dict], lr: float) -> Stage:
    """A stage of the VAE's decoder that draws the layout (its label maps, its LiDAR): the layout's
    config sections, 1500 steps of 16 frames by default."""
    return Stage(
        kind,
        train,
        16,
        lr,
        100,
        config_sections=("sensors", "vae", "layout"),
        steps={"default": 1500},
        check=check_decoder_config,
    )


# Sized for the 2-core CPU (docs/MODEL_CARD.md lists the measured seconds per step): one ``ode`` step
# runs the TF model's 20-step guided ODE, one ``dmd``/``long`` step runs 1 + critic_updates self-rollouts.
REGISTRY: dict[str, Stage] = {
    s.name: s
    for s in (
        Stage("vae", vae_stage, 16, 2e-3, 100, config_sections=("sensors", "vae")),
        # the decoder again, drawing the layout's label maps, on the frozen encoder's latents
        _decoder("decoder", decoder_stage, 5e-4),
        Stage("teacher", teacher_stage, 4, 1e-3, 100, config_sections="teacher"),
        _student("tf", 4, 5e-4, 100, 500),
        _student("ode", 4, 5e-4, 20, 80),  # an ode step runs a 20-step guided ODE: checkpoint often
        _student("dmd", 2, 1e-4, 10, 50),  # each dmd/long step = 1 + critic_updates self-rollouts
        _student("long", 2, 5e-5, 10, 20),
        # long's objective at fewer denoising steps, from the long student (or a bundle's)
        _student("steps", 2, 5e-5, 10, 150),
        # the finished student distilled into dit.student_depth blocks: a cheaper env step
        Stage("shallow", shallow_stage, 4, 1e-4, 100, steps={"default": 3000}),
        Stage("reference", reference_stage, 4, 5e-4, 100, config_sections="teacher", steps={"default": 800}),
        # the reference model's first frames from controls in one unguided step (env.reset())
        Stage("first_frame", first_frame_stage, 8, 1e-4, 250, config_sections="teacher", steps={"default": 1500}),
        # the decoder once more, on the trained student's own rollouts streamed as the env does
        _decoder("rollout_decoder", rollout_decoder_stage, 2e-4),
        # the VAE's range head alone, on the student's rollouts: the LiDAR at the range map's resolution
        _decoder("range_head", range_head_stage, 1e-3),
        # the cameras' own copy of the decoder, on the rollouts' camera frames: the LiDAR stays as it is
        _decoder("camera_decoder", camera_decoder_stage, 2e-4),
        Stage(
            "lora",
            lora_stage,
            4,
            1e-3,
            50,
            LoraStageOptions,
            lora_setup,
            directory=lambda run, options: lora_stage_dir(run, options.case),
            steps=LORA_STEPS,
        ),
    )
}
STAGES = tuple(REGISTRY)
DEFAULT_STEPS = {"tiny": 50, "default": 3000, "gpu": 100_000}
# The stage options that change a model, by their CLI flags: a stage that does not own one refuses
# it when given (the data options are dropped: one command line may carry a whole chain's flags,
# as ``--all`` does).
MODEL_OPTION_FLAGS = {"base": "--base", "box_weight": "--lora-box-weight", "rank": "--lora-rank"}


def _spec(stage: str) -> Stage:
    if stage not in REGISTRY:
        raise ValueError(f"unknown stage {stage!r}; choose one of {STAGES}")
    return REGISTRY[stage]


def _fields(kind: type) -> set[str]:
    return {f.name for f in dataclasses.fields(kind)}


def stage_options(stage: str, **settings: Any) -> StageOptions:
    """``stage``'s options (its :attr:`Stage.options` type) from a whole chain's ``settings`` (the
    fields of every stage's options type): those of its type are kept and the others dropped, save
    a model setting of another stage given (:data:`MODEL_OPTION_FLAGS`), refused by its flag."""
    spec = _spec(stage)
    unknown = sorted(set(settings) - set().union(*(_fields(s.options) for s in REGISTRY.values())))
    if unknown:
        raise TypeError(f"unknown stage option(s) {unknown}")
    own = _fields(spec.options)
    for name, flag in MODEL_OPTION_FLAGS.items():
        value = settings.get(name)
        if name in own or value is None or (name == "box_weight" and not value):
            continue
        owners = " and ".join(f"--stage {s.name}" for s in REGISTRY.values() if name in _fields(s.options))
        raise ValueError(f"{flag} is a setting of {owners}, not of {stage!r}")
    return spec.options(**{name: value for name, value in settings.items() if name in own})


def _stage_config(stage_dir: Path, stage: Stage, options: StageOptions) -> ModelConfig:
    cfg = options.config or get_preset(options.preset)
    saved = stage_dir / "model_config.json"

    def relevant(c: ModelConfig) -> object:
        if stage.config_sections == "teacher":  # full-depth bidirectional: student settings do not touch it
            return c.teacher_settings()
        if stage.config_sections is None:  # the DiT stages: whatever decodes their latents
            return without_label_decoder(c)
        return tuple(getattr(c, name) for name in stage.config_sections)

    if saved.exists():
        prev = ModelConfig.from_dict(json.loads(saved.read_text()))
        if relevant(prev) != relevant(cfg):
            raise ValueError(
                f"{stage_dir} was started with preset {prev.name!r} and a different config; "
                "use the same preset to resume, or a new run directory"
            )
    else:
        stage_dir.mkdir(parents=True, exist_ok=True)
        write_json_atomic(saved, cfg.to_dict())
    return cfg


def _train_config(stage: str, cfg: ModelConfig, options: StageOptions) -> TrainConfig:
    spec = REGISTRY[stage]
    preset_steps = DEFAULT_STEPS.get(cfg.name, DEFAULT_STEPS["default"])
    if isinstance(spec.steps, int):
        preset_steps = spec.steps
    elif spec.steps:
        preset_steps = spec.steps.get(cfg.name, preset_steps)
    n = options.steps if options.steps is not None else preset_steps
    if n < 1:
        raise ValueError(f"steps must be >= 1, got {n}")
    return TrainConfig(
        steps=n,
        batch_size=options.batch_size or spec.batch_size,
        lr=options.lr or spec.lr,
        ckpt_every=options.ckpt_every or spec.ckpt_every,
        seed=options.seed,
    )


def train_stage(
    stage: str,
    data: str | Path,
    run: str | Path,
    options: StageOptions | None = None,
    runtime: StageRuntime | None = None,
) -> dict:
    """Train (or resume) one stage of the dataset ``data`` into ``run/<stage>/``; returns a summary dict.

    ``options``: the stage's own options type (:attr:`Stage.options`; None: its defaults; see
    :func:`stage_options`). ``runtime``: how this process trains it (:class:`StageRuntime`: precision,
    device, compilation and time limit, which checkpoints and their configs do not record)."""
    runtime = runtime or StageRuntime()
    deadline = None if runtime.time_limit_s is None else time.perf_counter() + runtime.time_limit_s
    spec = _spec(stage)
    options = spec.options() if options is None else options
    if type(options) is not spec.options:
        raise ValueError(f"--stage {stage} takes {spec.options.__name__}, got {type(options).__name__}")
    check_dtype(runtime.dtype)
    place = runtime.place or TrainPlace(resolve_device(runtime.device))
    kwargs = spec.setup(options) if spec.setup else {}
    run_root = Path(run)
    stage_dir = spec.directory(run_root, options) if spec.directory else run_root / stage
    if spec.check:
        spec.check(options.config or get_preset(options.preset))
    if place.is_main:  # writes the stage's config; the other ranks then check theirs against it
        _stage_config(stage_dir, spec, options)
    place.barrier()
    cfg = _stage_config(stage_dir, spec, options)
    tcfg = _train_config(stage, cfg, options)
    place.local_rows(tcfg.batch_size)  # an uneven shard is refused before any training
    loop = LoopOptions(progress=runtime.progress, compile_model=runtime.compile_model, deadline=deadline)
    stage_run = StageRun(Path(data), run_root, stage_dir, cfg, tcfg, place, loop)
    with dit_precision(resolve_bf16(runtime.dtype, cfg.dit.autocast_bf16, place.device)):
        out = spec.train(stage_run, **kwargs)
    place.barrier()  # rank 0's export is written before any rank starts the stage that reads it
    return {"stage": stage, "stage_dir": str(stage_dir), **out}
