"""The training stages and :func:`train_stage`, which runs one of them into ``RUN/<stage>/``.

A run directory holds one sub-directory per stage::

    RUN_DIR/vae/       checkpoints/, model.safetensors + model.json (EMA weights), metrics.json
    RUN_DIR/teacher/   checkpoints/, latents/ (the run's latent cache, every stage), model.safetensors + model.json
    RUN_DIR/tf|ode|dmd|long/  the causal student's stages (world_model.train.student_stages)
    RUN_DIR/reference/ the reference-conditioned model (world_model.train.reference_stage)
    RUN_DIR/rollout_decoder/  the decoder fine-tuned on the student's rollouts (world_model.train.rollout_decoder_stage)
    RUN_DIR/lora/CASE/ one LoRA adapter per long-tail case (world_model.train.lora_stage)

Each stage reads the exports of the stages before it. Rerunning a command resumes from the stage's
latest checkpoint; a finished stage rerun with a larger ``steps`` continues training.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from world_model.data.clips import write_json_atomic
from world_model.model.config import ModelConfig, get_preset, without_label_decoder
from world_model.precision import check_dtype, dit_precision, resolve_bf16
from world_model.student.config import StudentConfig
from world_model.train.device import TrainPlace, resolve_device
from world_model.train.lora_stage import LORA_STEPS, lora_options, lora_stage, lora_stage_dir
from world_model.train.reference_stage import reference_stage
from world_model.train.rollout_decoder_stage import rollout_decoder_stage
from world_model.train.run import StageRun
from world_model.train.student_stages import student_stage
from world_model.train.teacher_stage import teacher_stage
from world_model.train.trainer import TrainConfig
from world_model.train.vae_stage import check_decoder_config, decoder_stage, vae_stage


@dataclass(frozen=True)
class Stage:
    """One stage of the registry: how it trains, its defaults and the options it owns.

    ``options``: the keyword arguments of :func:`train_stage` (and so the CLI flags) that only this
    stage reads; any other stage refuses those that change a model by name. ``setup`` turns them
    into the keyword arguments of ``train`` (checked before anything is written) and ``directory``
    places the stage in the run (default ``RUN/<name>``). ``config_sections``: the config sections
    its weights depend on (None: the whole config; ``"teacher"``: :meth:`ModelConfig.teacher_settings`).
    """

    name: str
    train: Callable[..., dict]  # (StageRun, **options) -> summary
    batch_size: int  # CPU-sized defaults
    lr: float
    ckpt_every: int
    options: tuple[str, ...] = ()
    setup: Callable[..., dict] | None = None  # (**options) -> keyword arguments of train
    directory: Callable[[Path, dict], Path] | None = None  # (RUN, options) -> the stage's directory
    config_sections: tuple[str, ...] | str | None = None
    # Default steps where a step costs far more than a teacher's: per preset, or one count for all.
    steps: dict[str, int] | int | None = None
    check: Callable[[ModelConfig], None] | None = None  # refuses a config before anything is written


# Sized for the 2-core CPU (docs/MODEL_CARD.md lists the measured seconds per step): one ``ode`` step
# runs the TF model's 20-step guided ODE, one ``dmd``/``long`` step runs 1 + critic_updates self-rollouts.
REGISTRY: dict[str, Stage] = {
    s.name: s
    for s in (
        Stage("vae", vae_stage, 16, 2e-3, 100, config_sections=("sensors", "vae")),
        # the decoder again, drawing the layout's label maps, on the frozen encoder's latents
        Stage(
            "decoder",
            decoder_stage,
            16,
            5e-4,
            100,
            config_sections=("sensors", "vae", "layout"),
            steps={"default": 1500},
            check=check_decoder_config,
        ),
        Stage("teacher", teacher_stage, 4, 1e-3, 100, config_sections="teacher"),
        Stage("tf", partial(student_stage, "tf"), 4, 5e-4, 100, steps={"default": 500}),
        # an ode step runs a 20-step guided ODE: checkpoint often
        Stage("ode", partial(student_stage, "ode"), 4, 5e-4, 20, steps={"default": 80}),
        # each dmd/long step = 1 + critic_updates self-rollouts
        Stage("dmd", partial(student_stage, "dmd"), 2, 1e-4, 10, steps={"default": 50}),
        Stage("long", partial(student_stage, "long"), 2, 5e-5, 10, steps={"default": 20}),
        Stage("reference", reference_stage, 4, 5e-4, 100, config_sections="teacher", steps={"default": 800}),
        # the decoder once more, on the trained student's own rollouts streamed as the env does
        Stage(
            "rollout_decoder",
            rollout_decoder_stage,
            16,
            2e-4,
            100,
            config_sections=("sensors", "vae", "layout"),
            steps={"default": 1500},
            check=check_decoder_config,
        ),
        Stage(
            "lora",
            lora_stage,
            4,
            1e-3,
            50,
            ("case", "case_data", "case_clips", "base", "lora_box_weight", "lora_rank"),
            setup=lora_options,
            directory=lambda run, options: lora_stage_dir(run, options["case"]),
            steps=LORA_STEPS,
        ),
    )
}
STAGES = tuple(REGISTRY)
DEFAULT_STEPS = {"tiny": 50, "default": 3000, "gpu": 100_000}
# The CLI flag of each stage option, for the errors that refuse one.
OPTION_FLAGS = {
    "case": "--case",
    "case_data": "--case-data",
    "case_clips": "--case-clips",
    "base": "--base",
    "lora_box_weight": "--lora-box-weight",
    "lora_rank": "--lora-rank",
}


def _stage_config(stage_dir: Path, stage: Stage, preset: str, config: ModelConfig | None) -> ModelConfig:
    cfg = config or get_preset(preset)
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


def _train_config(
    stage: str,
    cfg: ModelConfig,
    steps: int | None,
    batch_size: int | None,
    lr: float | None,
    ckpt_every: int | None,
    seed: int,
) -> TrainConfig:
    spec = REGISTRY[stage]
    preset_steps = DEFAULT_STEPS.get(cfg.name, DEFAULT_STEPS["default"])
    if isinstance(spec.steps, int):
        preset_steps = spec.steps
    elif spec.steps:
        preset_steps = spec.steps.get(cfg.name, preset_steps)
    n = steps if steps is not None else preset_steps
    if n < 1:
        raise ValueError(f"steps must be >= 1, got {n}")
    return TrainConfig(
        steps=n,
        batch_size=batch_size or spec.batch_size,
        lr=lr or spec.lr,
        ckpt_every=ckpt_every or spec.ckpt_every,
        seed=seed,
    )


def _check_options(stage: str, given: dict[str, object]) -> None:
    """Refuse an option that belongs to another stage, naming its flag and its stages."""
    for name, value in given.items():
        if value is None or (name == "lora_box_weight" and not value) or name in REGISTRY[stage].options:
            continue
        owners = " and ".join(f"--stage {s.name}" for s in REGISTRY.values() if name in s.options)
        raise ValueError(f"{OPTION_FLAGS[name]} is a setting of {owners}, not of {stage!r}")


def train_stage(
    stage: str,
    data_dir: str | Path,
    run_dir: str | Path,
    preset: str = "default",
    steps: int | None = None,
    *,
    batch_size: int | None = None,
    lr: float | None = None,
    ckpt_every: int | None = None,
    seed: int = 0,
    progress: bool = True,
    config: ModelConfig | None = None,
    case: str | None = None,
    case_data: str | Path | None = None,
    case_clips: list[str] | None = None,
    base: str | Path | None = None,
    lora_box_weight: float = 0.0,
    lora_rank: int | None = None,
    student: StudentConfig | None = None,
    dtype: str = "auto",
    device: str = "cpu",
    place: TrainPlace | None = None,
    compile_model: bool = False,
    time_limit_s: float | None = None,
) -> dict:
    """Train (or resume) one stage into ``run_dir/<stage>/``; returns a summary dict.

    ``config`` overrides the preset's config (it must then stay the same across resumes);
    ``student`` configures the student stages (``tf``, ``ode``, ``dmd``, ``long``).
    ``lora`` only: ``case`` names the adapter (and the rare category), ``case_data`` an extra
    dataset of rare clips, ``case_clips`` explicit rare clip names, ``base`` the model adapted
    (default ``run_dir/teacher/model``), ``lora_box_weight`` the extra loss weight inside the rare
    object's boxes (``LoraStageConfig.box_weight``), ``lora_rank`` the adapter's rank (None: ``LoraConfig``'s).
    ``dtype``: the DiTs' autocast in this process, "auto" (bf16 when the config asks for it and the
    device multiplies bf16 natively: elsewhere bf16 is emulated and several times slower), "float32"
    or "bfloat16". ``device``: ``auto``, ``cpu``, ``cuda`` or ``cuda:N``; ``place`` (a process of a
    ``torchrun`` group, :func:`world_model.train.device.init_place`) overrides it. ``compile_model``:
    ``torch.compile`` the trained networks. ``time_limit_s``: the stage stops this many seconds after
    this call, its setup (caches, rollouts) counted, checkpointed and exported, even short of
    ``steps`` (after one step at least). Precision, device, compilation
    and time limit are run-time choices: checkpoints and their configs do not record them.
    """
    deadline = None if time_limit_s is None else time.perf_counter() + time_limit_s
    if stage not in REGISTRY:
        raise ValueError(f"unknown stage {stage!r}; choose one of {STAGES}")
    spec = REGISTRY[stage]
    # The settings that change a model are refused by any other stage; the data options are not
    # (one command line may carry a whole chain's flags, as ``--all`` does).
    _check_options(stage, {"base": base, "lora_box_weight": lora_box_weight, "lora_rank": lora_rank})
    check_dtype(dtype)
    place = place or TrainPlace(resolve_device(device))
    given = {"case": case, "case_data": case_data, "case_clips": case_clips, "base": base}
    given |= {"lora_box_weight": lora_box_weight, "lora_rank": lora_rank}
    options = {name: given[name] for name in spec.options}
    kwargs = spec.setup(**options) if spec.setup else {}
    run_root = Path(run_dir)
    stage_dir = spec.directory(run_root, options) if spec.directory else run_root / stage
    if spec.check:
        spec.check(config or get_preset(preset))
    if place.is_main:  # writes the stage's config; the other ranks then check theirs against it
        _stage_config(stage_dir, spec, preset, config)
    place.barrier()
    cfg = _stage_config(stage_dir, spec, preset, config)
    tcfg = _train_config(stage, cfg, steps, batch_size, lr, ckpt_every, seed)
    place.local_rows(tcfg.batch_size)  # an uneven shard is refused before any training
    run = StageRun(
        Path(data_dir),
        run_root,
        stage_dir,
        cfg,
        tcfg,
        place,
        progress,
        student or StudentConfig(),
        compile_model,
        deadline,
    )
    with dit_precision(resolve_bf16(dtype, cfg.dit.autocast_bf16, place.device)):
        out = spec.train(run, **kwargs)
    place.barrier()  # rank 0's export is written before any rank starts the stage that reads it
    return {"stage": stage, "stage_dir": str(stage_dir), **out}
