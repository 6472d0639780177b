"""Per-case LoRA adapters for the world model (paper §5), built on ``peft``.

Adapters sit on the DiT blocks' attention and MLP projections (layers named ``q``, ``k``, ``v``,
``o``, ``fc1``, ``fc2``; the control tokenizer and embeddings stay untouched) and are injected
in place into a :class:`~world_model.model.MultiViewDiT`, so whoever holds the model (the env's
backend) keeps the same object. The base weights are never modified: applying then removing
adapters restores outputs exactly.

On disk an adapter is two files in one directory (``DIR/<name>/`` of ``--stage lora``)::

    adapter.safetensors   LoRA tensors only (keys without the peft adapter name)
    adapter.json          {"format": "m4world-lora", "version", "name", "base_sha256",
                           "base_file_sha256", "lora": LoraConfig, "model_config", "train": {...}}

``base_sha256`` is :func:`base_fingerprint` of the model the adapter was trained on: the sha256
of its base weights' content (sorted names, shapes, values rounded to bf16), so it does not
depend on how a checkpoint file was serialized nor on float32 vs bf16 copies of the same base.
Loading onto a model with another fingerprint fails.

Name resolution of :func:`apply_adapters`: an existing path (an adapter directory or its
``.json``/``.safetensors`` file) is used as is; a bare name is looked up as ``<dir>/<name>/`` in
``search_dirs``, then in ``$M4WORLD_ADAPTERS`` (``os.pathsep``-separated), then in the package's
``world_model/checkpoints/adapters``.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import sys
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from safetensors.torch import load_file, save_file
from torch import nn

if TYPE_CHECKING:
    import peft  # optional dependency (the 'lora' extra)

FORMAT = "m4world-lora"
VERSION = 1
WEIGHTS, META = "adapter.safetensors", "adapter.json"
PACKAGE_ADAPTERS = Path(__file__).resolve().parent / "checkpoints" / "adapters"
ENV_VAR = "M4WORLD_ADAPTERS"
_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_-]*$")


class AdapterMismatchError(ValueError):
    """An adapter trained on another base model (different weights or architecture)."""


@dataclass(frozen=True)
class LoraConfig:
    """LoRA hyper-parameters (paper §5: a few hundred iterations, base frozen)."""

    rank: int = 8
    alpha: float = 8.0  # scale = alpha / rank
    dropout: float = 0.0
    target_modules: tuple[str, ...] = ("q", "k", "v", "o", "fc1", "fc2")
    scope: str = r"blocks\.\d+"  # module-path prefix: only the DiT blocks are adapted

    def __post_init__(self) -> None:
        if not (isinstance(self.rank, int) and self.rank >= 1):
            raise ValueError(f"the LoRA rank must be an integer >= 1, got {self.rank!r}")

    def with_rank(self, rank: int) -> LoraConfig:
        """The same adapter at another rank, its update scale (alpha / rank) kept."""
        return replace(self, rank=rank, alpha=self.alpha / self.rank * rank)

    def peft_config(self) -> peft.LoraConfig:
        import peft

        pattern = rf"{self.scope}\.(?:.*\.)?(?:{'|'.join(map(re.escape, self.target_modules))})"
        return peft.LoraConfig(r=self.rank, lora_alpha=self.alpha, lora_dropout=self.dropout, target_modules=pattern)


@dataclass
class AdapterInfo:
    """What a loaded adapter's JSON says (see the module docstring)."""

    name: str
    base_sha256: str
    lora: LoraConfig
    meta: dict = field(default_factory=dict)

    @property
    def completes(self) -> str | None:
        """The object category this adapter completes, for an adapter trained on a reference
        model in the completion task (``--stage lora --base RUN/reference/model``: its rare windows
        regenerate that category's boxes, ``train.reference_tasks``); None for any other adapter.
        The category is ``train.case``; adapters trained before it was recorded were named after it."""
        train = self.meta.get("train", {})
        return train.get("case", self.name) if train.get("reference_tasks") else None


def _check_name(name: str) -> str:
    if not _NAME.match(name):
        raise ValueError(f"adapter name {name!r} must be letters, digits, '_' or '-' (it names a directory)")
    return name


def _lora_layers(model: nn.Module) -> list[tuple[str, nn.Module]]:
    if "peft.tuners.lora" not in sys.modules:
        # No LoRA layer can exist before peft's is imported; importing it for nothing would pull in
        # transformers (seconds and ~150 MB of resident memory) on every adapter-free rollout.
        return []
    from peft.tuners.lora import LoraLayer

    return [(n, m) for n, m in model.named_modules() if isinstance(m, LoraLayer)]


def loaded_adapters(model: nn.Module) -> list[str]:
    """Names of the adapters injected into ``model`` (in injection order), whichever layers they target."""
    names: dict[str, None] = {}
    for _, layer in _lora_layers(model):
        names.update(dict.fromkeys(layer.lora_A.keys()))
    return list(names)


def base_state(model: nn.Module) -> dict[str, torch.Tensor]:
    """The model's state dict without LoRA tensors, under the base model's own key names."""
    out = {}
    for k, v in model.state_dict().items():
        if ".lora_" in k:
            continue
        out[k.replace(".base_layer.", ".")] = v
    return out


def base_fingerprint(model: nn.Module) -> str:
    """sha256 of the base weights' content (names, shapes, values rounded to bfloat16); LoRA
    tensors excluded. Rounding makes the float32 model an adapter was trained on and the bf16 copy
    the runtime serves (bundles store the DiTs in bf16) the same base."""
    h = hashlib.sha256()
    for k, v in sorted(base_state(model).items()):
        t = v.detach().cpu()
        t = (t.to(torch.bfloat16) if t.is_floating_point() else t).contiguous()
        h.update(f"{k}|{tuple(t.shape)}\n".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def _set_active(model: nn.Module, names: list[str], trainable: str | None) -> None:
    """Activate ``names`` in every LoRA layer; only adapter ``trainable`` gets gradients."""
    for _, layer in _lora_layers(model):
        layer.set_adapter(names) if names else layer.set_adapter([])
    for n, p in model.named_parameters():
        p.requires_grad_(trainable is not None and ".lora_" in n and f".{trainable}." in n)


@contextmanager
def only_adapters(model: nn.Module, names: Sequence[str]) -> Iterator[None]:
    """Within the block only the loaded adapters ``names`` act (none: the base model); the adapters
    active before are restored after it, also after an exception. No parameter's ``requires_grad``
    changes, inside the block or after it (a compiled graph keyed on it is not recompiled)."""
    loaded = loaded_adapters(model)
    unknown = [n for n in names if n not in loaded]
    if unknown:
        raise KeyError(f"adapters {unknown} are not loaded; loaded: {loaded}")
    layers = [layer for _, layer in _lora_layers(model)]
    before = [list(layer.active_adapters) for layer in layers]
    grads = [(p, p.requires_grad) for layer in layers for p in layer.parameters()]  # peft's set_adapter sets them
    try:
        for layer in layers:
            layer.set_adapter(list(names), inference_mode=True)
        for p, requires_grad in grads:  # inference_mode froze the active ones: put every flag back
            p.requires_grad_(requires_grad)
        yield
    finally:
        for layer, active in zip(layers, before, strict=True):
            layer.set_adapter(active)
        for p, requires_grad in grads:
            p.requires_grad_(requires_grad)


def add_adapter(model: nn.Module, name: str, cfg: LoraConfig | None = None) -> list[nn.Parameter]:
    """Inject a fresh adapter ``name`` (B = 0, so outputs are unchanged); freeze everything else.

    Returns the adapter's trainable parameters.
    """
    import peft

    _check_name(name)
    if name in loaded_adapters(model):
        raise ValueError(f"adapter {name!r} is already loaded; remove_adapters(model, [{name!r}]) first")
    active = loaded_adapters(model)
    with warnings.catch_warnings():
        # peft warns that a second adapter joins the first: stacking adapters is intended here.
        warnings.filterwarnings("ignore", message="Already found a `peft_config`")
        peft.inject_adapter_in_model((cfg or LoraConfig()).peft_config(), model, adapter_name=name)
    _set_active(model, [*active, name], trainable=name)
    return [p for p in model.parameters() if p.requires_grad]


def adapter_state(model: nn.Module, name: str) -> dict[str, torch.Tensor]:
    """Adapter ``name``'s tensors, keyed without the adapter name (``...q.lora_A.weight``)."""
    tag = f".{name}."
    out = {k.replace(tag, "."): v for k, v in model.state_dict().items() if ".lora_" in k and tag in k}
    if not out:
        raise KeyError(f"no adapter {name!r} in the model; loaded: {loaded_adapters(model)}")
    return out


def save_adapter(
    model: nn.Module,
    name: str,
    out_dir: str | Path,
    cfg: LoraConfig,
    base_sha256: str,
    extra_meta: dict | None = None,
) -> Path:
    """Write adapter ``name`` to ``out_dir/adapter.{safetensors,json}`` atomically; returns out_dir."""
    from world_model.data.clips import sha256_file, write_json_atomic

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / f".{WEIGHTS}.{os.getpid()}.tmp"
    save_file({k: v.detach().cpu().contiguous() for k, v in adapter_state(model, name).items()}, str(tmp))
    os.replace(tmp, out / WEIGHTS)
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "name": name,
        "base_sha256": base_sha256,
        "lora": {**asdict(cfg), "target_modules": list(cfg.target_modules)},
        **(extra_meta or {}),
        "weights_sha256": sha256_file(out / WEIGHTS),
    }
    write_json_atomic(out / META, meta)
    return out


def seal_adapter(path: str | Path) -> Path:
    """Record the sha256 of an adapter's weights in its ``adapter.json`` (after a deliberate edit)."""
    from world_model.data.clips import sha256_file, write_json_atomic

    path = Path(path)
    meta = _read_meta(path)
    meta["weights_sha256"] = sha256_file(path / WEIGHTS)
    write_json_atomic(path / META, meta)
    return path


class AdapterError(ValueError):
    """An adapter folder whose files are missing, corrupt or tampered with. The message names the file."""


def _read_meta(path: Path) -> dict:
    try:
        meta = json.loads((path / META).read_bytes().decode("utf-8"))
    except FileNotFoundError as e:
        raise AdapterError(f"{path / META} is missing") from e
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
        raise AdapterError(f"{path / META} is corrupt (not valid JSON in UTF-8: {e})") from e
    if not isinstance(meta, dict) or meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise AdapterError(f"{path / META} is not a {FORMAT} v{VERSION} adapter")
    return meta


def resolve_adapter(name_or_path: str | Path, search_dirs: Sequence[str | Path] = ()) -> Path:
    """The directory holding an adapter, from a path or a name (module docstring)."""
    p = Path(name_or_path)
    if p.is_file() and p.name in (WEIGHTS, META):
        return p.parent
    if p.is_dir() and (p / META).exists():
        return p
    env = [d for d in os.environ.get(ENV_VAR, "").split(os.pathsep) if d]
    dirs = [Path(d) for d in (*search_dirs, *env)] + [PACKAGE_ADAPTERS]
    if _NAME.match(str(name_or_path)):
        for d in dirs:
            if (d / str(name_or_path) / META).exists():
                return d / str(name_or_path)
    raise FileNotFoundError(
        f"adapter {str(name_or_path)!r} not found: not an adapter directory, and no "
        f"<dir>/{name_or_path}/{META} in {[str(d) for d in dirs]}; train one with "
        f"`python -m world_model.train --stage lora --case {name_or_path} ...` or set ${ENV_VAR}"
    )


def read_adapter(path: str | Path) -> tuple[AdapterInfo, dict[str, torch.Tensor]]:
    """An adapter directory -> (info, tensors)."""
    from world_model.data.clips import sha256_file

    path = Path(path)
    meta = _read_meta(path)
    weights = path / WEIGHTS
    if not weights.is_file():
        raise AdapterError(f"{weights} is missing")
    if meta.get("weights_sha256") != sha256_file(weights):
        raise AdapterError(
            f"{weights} does not match the sha256 recorded in {META} (corrupt, replaced, or written without one); "
            "retrain the adapter, or world_model.lora.seal_adapter() after a deliberate edit"
        )
    try:
        lora = meta["lora"]
        cfg = LoraConfig(**{**lora, "target_modules": tuple(lora["target_modules"])})
        info = AdapterInfo(name=meta["name"], base_sha256=meta["base_sha256"], lora=cfg, meta=meta)
    except (KeyError, TypeError, ValueError) as e:
        raise AdapterError(f"{path / META} is corrupt: {e!r}") from e
    tensors = load_file(str(weights))
    bad = [k for k, t in tensors.items() if t.is_floating_point() and not torch.isfinite(t).all()]
    if bad:
        raise AdapterError(f"{weights} holds non-finite weights (NaN or inf) in {bad[:5]}")
    return info, tensors


def apply_adapters(
    model: nn.Module, names_or_paths: Sequence[str | Path], search_dirs: Sequence[str | Path] = ()
) -> list[str]:
    """Load adapters (names or paths) into ``model`` in place and activate them all (their
    updates add up). Every adapter must have been trained on this exact base model
    (:class:`AdapterMismatchError` otherwise). Returns the adapter names now active."""
    if not names_or_paths:
        return loaded_adapters(model)
    base = base_fingerprint(model)
    loaded = []
    for item in names_or_paths:
        path = resolve_adapter(item, search_dirs)
        info, tensors = read_adapter(path)
        if info.base_sha256 != base:
            raise AdapterMismatchError(
                f"adapter {info.name!r} ({path}) was trained on base weights {info.base_sha256[:16]}…, "
                f"but this model's weights are {base[:16]}…; retrain it with --base pointing at this model"
            )
        if info.name in loaded_adapters(model):
            raise ValueError(f"adapter {info.name!r} is already loaded")
        add_adapter(model, info.name, info.lora)
        tag = f".{info.name}."
        own = {k: v for k, v in model.state_dict().items() if ".lora_" in k and tag in k}
        renamed = {k.replace(tag, "."): k for k in own}
        if set(renamed) != set(tensors):
            remove_adapters(model, [info.name])
            raise AdapterMismatchError(f"adapter {info.name!r} ({path}) does not fit this model's layers")
        model.load_state_dict({renamed[k]: v for k, v in tensors.items()}, strict=False)
        loaded.append(info.name)
    _set_active(model, loaded_adapters(model), trainable=None)
    return loaded_adapters(model)


def remove_adapters(model: nn.Module, names: Sequence[str] | None = None) -> list[str]:
    """Remove adapters ``names`` (default: all). When none remain, every LoRA layer is replaced by
    its original layer, so the model is again exactly the base model. Returns the remaining names."""
    current = loaded_adapters(model)
    names = list(current if names is None else names)
    unknown = [n for n in names if n not in current]
    if unknown:
        raise KeyError(f"adapters {unknown} are not loaded; loaded: {current}")
    remaining = [n for n in current if n not in names]
    if remaining:
        with warnings.catch_warnings():
            # peft warns when an active adapter goes; the remaining ones are activated right below.
            warnings.filterwarnings("ignore", message="Adapter .* was active which is now deleted")
            for _, layer in _lora_layers(model):
                for n in names:
                    layer.delete_adapter(n)
        _set_active(model, remaining, trainable=None)
        return remaining
    for path, layer in _lora_layers(model):
        parent_name, _, child = path.rpartition(".")
        parent = model.get_submodule(parent_name) if parent_name else model
        setattr(parent, child, layer.get_base_layer())
    for p in model.parameters():
        p.requires_grad_(True)
    for attr in ("peft_config", "_hf_peft_config_loaded"):
        if attr in model.__dict__:
            del model.__dict__[attr]
    return []
