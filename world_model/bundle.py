"""A world-model checkpoint *bundle*: everything the env's world-model backend loads, in one folder.

Layout::

    BUNDLE/
      manifest.json            format, version, the student's model config, and per component: file,
                               sha256, bytes, stage, and ``model_config`` where the component's
                               differs (the reference model: wider input, teacher depth)
      vae.safetensors          the shared camera/LiDAR autoencoder (stage ``camera_decoder``, else
                               ``range_head``, else ``rollout_decoder``, else ``decoder``, else ``vae``)
      student.safetensors      the causal few-step student (stage ``steps``, else ``long``, else ``dmd``)
      reference.safetensors    the reference-conditioned first-frame model (stage ``reference``), optional
      first_frame.safetensors  the one-step first-frame model (stage ``first_frame``), optional
      streaming.json           how the student streams at inference (denoising steps, context
                               refresh, sink frames: :class:`~world_model.streaming.StreamingConfig`)
      adapters/                optional LoRA adapters (``lora`` stage output)

:func:`export_bundle` collects the stage exports of a training run; :func:`load_bundle_files`
verifies every file against the manifest before anything is deserialized, so a missing, truncated
or tampered checkpoint fails with :class:`CheckpointError` naming the file, never deep in torch.
The shipped default bundle lives in ``world_model/checkpoints/default`` (package data).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file

from world_model.data.clips import sha256_file, write_json_atomic
from world_model.lora import META, WEIGHTS
from world_model.streaming import STREAMING_FILE, StreamingConfig, taught_streaming
from world_model.student.config import StudentConfig

BUNDLE_FORMAT = "m4world-bundle"
BUNDLE_VERSION = 1
DEFAULT_BUNDLE = Path(__file__).parent / "checkpoints" / "default"
# Component -> the run stages that may provide it, preferred first.
COMPONENT_STAGES = {
    "vae": ("camera_decoder", "range_head", "rollout_decoder", "decoder", "vae"),
    "student": ("shallow", "steps", "long", "dmd", "ode"),
    "reference": ("reference",),
    "first_frame": ("first_frame",),
}
REQUIRED = ("vae", "student")
RANGE_HEAD_STAGE = "range_head"  # finishes the decoder it was trained on (model.json: "finishes")
CAMERA_DECODER_STAGE = "camera_decoder"  # the VAE it started from, every weight of it kept
LABEL_DECODER_STAGES = ("rollout_decoder", "decoder")  # a range head's decoder: the first exported
CAMERA_DECODER_SOURCES = (RANGE_HEAD_STAGE, *LABEL_DECODER_STAGES)  # a camera decoder's VAE: the first exported
DIGEST_KEY = "digest"  # manifest.json: sha256 of the manifest's other fields and the bundle's other JSON files
BF16_COMPONENTS = ("student", "reference", "first_frame")  # DiTs; the VAE stays float32
# May differ from the student's config (input width, depth); the first-frame model has the reference model's.
OWN_CONFIG_COMPONENTS = ("reference", "first_frame")
BUNDLE_RECORD = "bundle_record"  # a seeded export's metadata: its component's manifest record (bundle_record)


class CheckpointError(ValueError):
    """A checkpoint bundle that is missing, incomplete, corrupt or of an unknown format."""


class CheckpointNotFoundError(CheckpointError, FileNotFoundError):
    """The checkpoint path does not exist."""


@dataclass
class BundleFiles:
    """Verified tensors and configs of a bundle (deserialized, not yet turned into modules)."""

    path: Path
    manifest: dict
    tensors: dict[str, dict[str, torch.Tensor]]  # component -> state dict
    streaming: dict | None = None  # streaming.json's content; None: a bundle without one

    @property
    def model_config(self) -> dict:
        """The student's config (the bundle's config: sensors, VAE, controls are shared)."""
        return self.manifest["model_config"]

    def component_config(self, component: str) -> dict | None:
        """``component``'s own model config when it differs from the student's (None: same, or a
        bundle written before components carried one)."""
        return self.manifest["components"][component].get("model_config")

    def has(self, component: str) -> bool:
        return component in self.tensors


def export_bundle(run_dir: str | Path, out_dir: str | Path, streaming: StreamingConfig | None = None) -> Path:
    """Collect the stage exports of ``run_dir`` into a bundle at ``out_dir`` (replaced atomically),
    with ``streaming`` as its ``streaming.json`` (default: :class:`StreamingConfig`'s defaults at the
    denoising steps the student was taught)."""
    run_dir, out_dir = Path(run_dir), Path(out_dir)
    found: dict[str, tuple[str, Path]] = {}
    for component, stages in COMPONENT_STAGES.items():
        for stage in stages:
            file = run_dir / stage / "model.safetensors"
            if file.exists():
                found[component] = (stage, file)
                break
    missing = [c for c in REQUIRED if c not in found]
    if missing:
        raise CheckpointError(
            f"{run_dir} has no export for {missing}: train stages {[COMPONENT_STAGES[c] for c in missing]} first"
        )
    if found["vae"][0] == CAMERA_DECODER_STAGE:
        _check_camera_decoder(run_dir)
    if found["vae"][0] in (CAMERA_DECODER_STAGE, RANGE_HEAD_STAGE) and (run_dir / RANGE_HEAD_STAGE).is_dir():
        _check_range_head(run_dir)
    student_meta = json.loads(found["student"][1].with_suffix(".json").read_text())
    config = student_meta["model_config"]
    # The decoder is the one component whose config may differ from the student's (the DiTs do
    # not depend on it): the bundle's VAE draws the scene exactly when a decoder stage made it,
    # finishes the LiDAR with a range head exactly when the range_head stage did (the camera
    # decoder keeps the head of the VAE it started from), and draws the cameras with a decoder of
    # their own exactly when the camera_decoder stage made it.
    vae_stage = found["vae"][0]
    layout = config.get("layout", {})
    vae_layout = (_export_config(found["vae"][1]) or {}).get("layout", {})
    drawn = {
        "decoder": vae_stage in (CAMERA_DECODER_STAGE, RANGE_HEAD_STAGE, *LABEL_DECODER_STAGES),
        "range_head": vae_stage == RANGE_HEAD_STAGE
        or (vae_stage == CAMERA_DECODER_STAGE and bool(vae_layout.get("range_head", False))),
        "camera_decoder": vae_stage == CAMERA_DECODER_STAGE,
    }
    changed = {key: value for key, value in drawn.items() if layout.get(key, False) != value}
    if changed:
        config["layout"] = {**layout, **changed}
    tmp = out_dir.with_name(out_dir.name + ".partial")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    components = {}
    # The runtime runs the DiTs with bf16 weights when the config says so: storing them in bf16
    # halves the bundle and changes no output.
    bf16 = bool(config.get("dit", {}).get("autocast_bf16", False))
    for component, (stage, file) in found.items():
        dst = tmp / f"{component}.safetensors"
        if bf16 and component in BF16_COMPONENTS:
            _save_bf16(file, dst)
        else:
            shutil.copyfile(file, dst)
        own = _export_config(file) if component in OWN_CONFIG_COMPONENTS else None
        components[component] = {**_entry(dst, stage, config, own), **_export_meta(file).get(BUNDLE_RECORD, {})}
    adapters = run_dir / "lora"
    if adapters.is_dir():
        shutil.copytree(adapters, tmp / "adapters", ignore=_adapter_files_only)
    taught = StudentConfig.from_dict(student_meta.get("student_config") or {}).num_steps
    _write_streaming(tmp, streaming or taught_streaming(taught))
    _write_manifest(tmp, config, components, student_meta.get("student_config"))
    if out_dir.exists():
        shutil.rmtree(out_dir)
    os.replace(tmp, out_dir)
    return out_dir


def _adapter_files_only(folder: str, names: list[str]) -> set[str]:
    """``copytree`` filter: adapter folders keep their two files, not the stage's checkpoints/logs."""
    return {n for n in names if n not in (META, WEIGHTS) and not (Path(folder) / n / META).exists()}


def _check_range_head(run_dir: Path) -> None:
    """Refuse a range head trained on another decoder than the run's latest one: a decoder stage
    trained again after it (or seeded from another bundle) needs the head trained again too."""
    from world_model.model.range_head import finished_digest

    head_meta = json.loads((run_dir / RANGE_HEAD_STAGE / "model.json").read_text())
    for stage in LABEL_DECODER_STAGES:
        file = run_dir / stage / "model.safetensors"
        if file.exists():
            if head_meta.get("finishes") != finished_digest(load_file(str(file))):
                raise CheckpointError(
                    f"{run_dir / RANGE_HEAD_STAGE} was trained on another decoder than {run_dir / stage}'s: "
                    f"train --stage {RANGE_HEAD_STAGE} again"
                )
            return


def _check_camera_decoder(run_dir: Path) -> None:
    """Refuse a camera decoder trained on another VAE than the run's latest one (a range head or a
    label decoder trained again after it): every weight of that VAE must be in it unchanged."""
    camera = load_file(str(run_dir / CAMERA_DECODER_STAGE / "model.safetensors"))
    for stage in CAMERA_DECODER_SOURCES:
        file = run_dir / stage / "model.safetensors"
        if file.exists():
            source = load_file(str(file))
            if any(key not in camera or not torch.equal(camera[key], value) for key, value in source.items()):
                raise CheckpointError(
                    f"{run_dir / CAMERA_DECODER_STAGE} was trained on another VAE than {run_dir / stage}'s: "
                    f"train --stage {CAMERA_DECODER_STAGE} again"
                )
            return


def _export_meta(file: Path) -> dict:
    meta = file.with_suffix(".json")
    return json.loads(meta.read_text()) if meta.exists() else {}


def _export_config(file: Path) -> dict | None:
    return _export_meta(file).get("model_config")


def bundle_record(entry: dict) -> dict:
    """What a manifest's component ``entry`` records beyond its file and config (how the component
    was made, e.g. the range head's ``tuned``): a run seeded from the bundle keeps it in the export
    it seeds (:data:`BUNDLE_RECORD`), and a bundle exported from that untouched export carries it."""
    return {k: v for k, v in entry.items() if k not in ("file", "sha256", "bytes", "stage", "model_config")}


def _entry(file: Path, stage: str, bundle_config: dict, own_config: dict | None) -> dict:
    entry = {"file": file.name, "sha256": sha256_file(file), "bytes": file.stat().st_size, "stage": stage}
    if own_config is not None and own_config != bundle_config:
        entry["model_config"] = own_config
    return entry


def _save_bf16(src: Path, dst: Path) -> None:
    from safetensors.torch import save_file

    state = load_file(str(src))
    save_file({k: v.to(torch.bfloat16) if v.is_floating_point() else v for k, v in state.items()}, str(dst))


def save_bundle(
    out_dir: str | Path,
    model_config: dict,
    components: dict[str, dict[str, torch.Tensor]],
    student_config: dict | None = None,
    stages: dict[str, str] | None = None,
    component_configs: dict[str, dict] | None = None,
    streaming: StreamingConfig | None = None,
) -> Path:
    """Write state dicts (``vae``, ``student``, optional ``reference``) as a bundle, atomically.
    ``model_config`` is the student's; ``component_configs`` the others' where they differ."""
    from safetensors.torch import save_file

    out_dir = Path(out_dir)
    missing = [c for c in REQUIRED if c not in components]
    if missing:
        raise CheckpointError(f"a bundle needs the {missing} component(s)")
    tmp = out_dir.with_name(out_dir.name + ".partial")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    entries = {}
    for name, state in components.items():
        dst = tmp / f"{name}.safetensors"
        save_file({k: v.detach().contiguous().cpu() for k, v in state.items()}, str(dst))
        own = (component_configs or {}).get(name)
        entries[name] = _entry(dst, (stages or {}).get(name, "unknown"), model_config, own)
    _write_streaming(tmp, streaming or StreamingConfig())
    _write_manifest(tmp, model_config, entries, student_config)
    if out_dir.exists():
        shutil.rmtree(out_dir)
    os.replace(tmp, out_dir)
    return out_dir


def _write_manifest(root: Path, model_config: dict, components: dict, student_config: dict | None) -> None:
    manifest = {
        "format": BUNDLE_FORMAT,
        "version": BUNDLE_VERSION,
        "model_config": model_config,
        "components": components,
    }
    if student_config is not None:
        manifest["student_config"] = student_config
    manifest[DIGEST_KEY] = bundle_digest(root, manifest)
    write_json_atomic(root / "manifest.json", manifest)


def _write_streaming(root: Path, streaming: StreamingConfig) -> None:
    write_json_atomic(root / STREAMING_FILE, streaming.to_dict())


def set_streaming(path: str | Path | None, streaming: StreamingConfig) -> Path:
    """Write ``streaming`` as the bundle's ``streaming.json`` and re-seal its manifest. The bundle is
    verified first, so a damaged bundle is never re-sealed."""
    files = load_bundle_files(path)
    _write_streaming(files.path, streaming)
    m = files.manifest
    _write_manifest(files.path, m["model_config"], m["components"], m.get("student_config"))
    return files.path


def bundle_digest(root: Path, manifest: dict) -> str:
    """sha256 over the manifest (configs, component hashes; its own digest left out) and every other
    JSON file in the bundle's folder, so that no config can change without the bundle noticing.
    Weight files are covered by their own hashes in the manifest."""
    h = hashlib.sha256()
    body = {k: v for k, v in manifest.items() if k != DIGEST_KEY}
    h.update(json.dumps(body, sort_keys=True, separators=(",", ":")).encode())
    for file in sorted(root.glob("*.json")):
        if file.name != "manifest.json":
            h.update(file.name.encode() + b"\0" + file.read_bytes())
    return h.hexdigest()


def reseal_bundle(path: str | Path) -> Path:
    """Rewrite ``path``'s manifest after its files were deliberately changed: the hashes and sizes of
    the listed weight files and the digest are recomputed. Refuses a bundle whose manifest is not one."""
    root = resolve_bundle(path)
    manifest = _read_manifest(root / "manifest.json")
    for info in _components(manifest, root / "manifest.json").values():
        file = root / info["file"]
        info.update(sha256=sha256_file(file), bytes=file.stat().st_size)
    _write_manifest(root, manifest["model_config"], manifest["components"], manifest.get("student_config"))
    return root


def _read_manifest(manifest_path: Path) -> dict:
    root = manifest_path.parent
    try:
        manifest = json.loads(manifest_path.read_bytes().decode("utf-8"))
    except FileNotFoundError as e:
        raise CheckpointError(f"{root} is not a checkpoint bundle: {manifest_path.name} is missing") from e
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
        raise CheckpointError(f"{manifest_path} is corrupt (not valid JSON in UTF-8: {e})") from e
    if not isinstance(manifest, dict) or not isinstance(manifest.get("components", {}), dict):
        raise CheckpointError(f"{manifest_path} is corrupt: not a bundle manifest (an object with 'components')")
    if manifest.get("format") != BUNDLE_FORMAT or manifest.get("version") != BUNDLE_VERSION:
        raise CheckpointError(
            f"{manifest_path}: format {manifest.get('format')!r} v{manifest.get('version')} is not "
            f"{BUNDLE_FORMAT!r} v{BUNDLE_VERSION}"
        )
    if not isinstance(manifest.get("model_config"), dict):
        raise CheckpointError(f"{manifest_path} is corrupt: 'model_config' must be an object")
    return manifest


def _components(manifest: dict, manifest_path: Path) -> dict[str, dict]:
    """The manifest's components, each checked for its fields; unknown components refused."""
    components = manifest.get("components", {})
    unknown = sorted(set(components) - set(COMPONENT_STAGES))
    if unknown:
        raise CheckpointError(
            f"{manifest_path}: unknown component(s) {unknown}; a bundle holds {list(COMPONENT_STAGES)}"
        )
    missing = [c for c in REQUIRED if c not in components]
    if missing:
        raise CheckpointError(f"{manifest_path} lists no {missing} component: the bundle is incomplete")
    for name, info in components.items():
        if not isinstance(info, dict) or not {"file", "bytes", "sha256"} <= set(info):
            raise CheckpointError(f"{manifest_path} is corrupt: component {name!r} needs 'file', 'bytes' and 'sha256'")
        file = info["file"]
        if not isinstance(file, str) or Path(file).name != file or file in ("", ".", ".."):
            raise CheckpointError(
                f"{manifest_path} is corrupt: component {name!r} 'file' must be a file name in the bundle, got {file!r}"
            )
    return components


def resolve_bundle(path: str | Path | None) -> Path:
    """``None`` → the shipped default bundle; a path must exist."""
    if path is not None and not isinstance(path, str | os.PathLike):
        raise CheckpointError(
            f"checkpoint must be a path to a bundle folder (or None for the shipped one), got {path!r}"
        )
    p = DEFAULT_BUNDLE if path is None else Path(path)
    if not p.exists():
        hint = (
            "this install has no default checkpoint (world_model/checkpoints/default); train one with "
            "`m4world train --all --data DIR --run RUN` and pass checkpoint='RUN/bundle'"
            if path is None
            else "give the folder written by `m4world export` or `m4world train --all` (RUN/bundle)"
        )
        raise CheckpointNotFoundError(f"checkpoint {p} does not exist: {hint}")
    return p


def load_bundle_files(path: str | Path | None = None) -> BundleFiles:
    """Read and verify a bundle. Raises :class:`CheckpointError` with the offending file named."""
    root = resolve_bundle(path)
    if not root.is_dir():
        raise CheckpointError(
            f"checkpoint {root} is a file; give the bundle folder that holds it and manifest.json ({root.parent})"
        )
    manifest_path = root / "manifest.json"
    manifest = _read_manifest(manifest_path)
    components = _components(manifest, manifest_path)
    if manifest.get(DIGEST_KEY) != bundle_digest(root, manifest):
        raise CheckpointError(
            f"{manifest_path}: the bundle's configs differ from what it was exported with (its digest does not "
            "match): export it again (`m4world export`), or world_model.bundle.reseal_bundle() after a deliberate edit"
        )
    tensors = {}
    for name, info in components.items():
        file = root / info["file"]
        if not file.exists():
            raise CheckpointError(f"checkpoint file {file} is missing (listed in {manifest_path.name})")
        if file.stat().st_size != info["bytes"] or sha256_file(file) != info["sha256"]:
            raise CheckpointError(f"checkpoint file {file} is corrupt: its size or sha256 differs from the manifest")
        try:
            tensors[name] = load_file(str(file))
        except SafetensorError as e:  # pragma: no cover - caught by the hash check first
            raise CheckpointError(f"checkpoint file {file} cannot be read: {e}") from e
        bad = [k for k, t in tensors[name].items() if t.is_floating_point() and not torch.isfinite(t).all()]
        if bad:
            raise CheckpointError(f"checkpoint file {file} holds non-finite weights (NaN or inf) in {bad[:5]}")
    return BundleFiles(path=root, manifest=manifest, tensors=tensors, streaming=read_streaming(root))


def streaming_config(root: Path, content: dict | None) -> StreamingConfig:
    """The :class:`StreamingConfig` of bundle ``root``'s ``streaming.json`` ``content``
    (:func:`read_streaming`; None: the defaults), a bad setting named by the file's path and key."""
    return StreamingConfig.from_dict(content or {}, str(root / STREAMING_FILE))


def read_streaming(root: Path) -> dict | None:
    """``streaming.json``'s content (covered by the manifest's digest), or None for a bundle without one."""
    file = root / STREAMING_FILE
    if not file.exists():
        return None
    try:
        return json.loads(file.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:  # pragma: no cover - caught by the digest first
        raise CheckpointError(f"{file} is not valid JSON: {e}") from e
