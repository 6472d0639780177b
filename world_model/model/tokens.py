"""Control tokenizer (§3.2): Conditions -> text, sensor and per-frame control tokens.

* text tokens: prompt token embeddings -> MLP;
* sensor tokens: Fourier embedding of each row of ``[K; R; t^T]`` -> MLP (one token per camera);
  the LiDAR, the reference frame, is a learned token;
* ego token: Fourier embedding of each row of ``[R_t; t_t^T]`` -> MLP (one token per frame);
* map tokens: the BEV raster patchified (``control.map_patch``) -> linear + learned 2-D position;
* object tokens: MLP(concat(Fourier(8 corners) -> MLP, pooled category-name embedding,
  image-description feature, text-description embedding)). A missing image or text description
  is replaced by a learned null feature; padding slots carry a learned pad token and are masked
  out of attention. Each object is tokenized on its own and object tokens get no positional
  encoding, so the order of objects does not matter.

Every key set carries one learned, always-visible null token: attention is then defined even
when a frame has no objects, and it is the only control left when ``Conditions.drop`` is set
(the unconditional branch of guidance; sensor tokens are kept so a view knows what it is).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import nn

from world_model.model.conditions import Conditions
from world_model.model.config import ModelConfig
from world_model.model.imagedesc import image_feature_dim


class FourierEmbed(nn.Module):
    """NeRF positional encoding: (..., 3) -> (..., 3 * (1 + 2F)) with frequencies 2^k * pi."""

    def __init__(self, num_freqs: int) -> None:
        super().__init__()
        self.register_buffer("freqs", torch.pi * 2.0 ** torch.arange(num_freqs), persistent=False)

    @property
    def out_per_vector(self) -> int:
        return 3 * (1 + 2 * len(self.freqs))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        angles = (x[..., None] * self.freqs).flatten(-2)
        return torch.cat([x, angles.sin(), angles.cos()], dim=-1)


def mlp(din: int, dout: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(din, dout), nn.SiLU(), nn.Linear(dout, dout))


def frame_rows(x: torch.Tensor, batch: int, frames: int, start: int, stop: int) -> torch.Tensor:
    """Rows (B*T, ...) laid out sample-major, one per frame -> those of frames [start, stop)."""
    return x.unflatten(0, (batch, frames))[:, start:stop].flatten(0, 1)


@dataclass
class ControlTokens:
    """text (B, L+1, D), text_mask (B, L+1); sensor (B, V, D); frame (B, T, Nf, D) with
    Nf = 1 ego + map tokens + max_objects + 1 null, frame_mask (B, T, Nf); view_adjacency (B, V, V);
    layout (B, T, V, Cl, h, w): the pixel-aligned layout the DiT concatenates to its input (not a
    token; it travels here so a forward given tokens has every control of its frames).

    ``cross_kv``: per DiT block, the keys/values its text and control cross-attentions compute
    from these tokens (``MultiViewDiT.tokenize`` fills it). They depend on the controls only, so
    the denoising steps of one chunk share them instead of projecting them again at every step.
    """

    text: torch.Tensor
    text_mask: torch.Tensor
    sensor: torch.Tensor
    frame: torch.Tensor
    frame_mask: torch.Tensor
    view_adjacency: torch.Tensor
    layout: torch.Tensor  # (B, T, V, LayoutConfig.channels, h, w), zero where the controls are dropped
    cross_kv: list[tuple[tuple[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]] | None = None

    def frames(self, start: int, stop: int) -> ControlTokens:
        """The tokens of frames [start, stop): per-frame tokens and the control keys/values (one
        row per batch sample and frame) sliced, the per-sequence ones shared."""
        b, t = self.frame.shape[:2]

        def rows(x: torch.Tensor) -> torch.Tensor:
            return frame_rows(x, b, t, start, stop)

        kv = None if self.cross_kv is None else [(text, (rows(k), rows(v))) for text, (k, v) in self.cross_kv]
        return replace(
            self,
            frame=self.frame[:, start:stop],
            frame_mask=self.frame_mask[:, start:stop],
            layout=self.layout[:, start:stop],
            cross_kv=kv,
        )


class ControlTokenizer(nn.Module):
    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        c = cfg.control
        d, dt, di = c.dim, cfg.text.dim, image_feature_dim(cfg)
        self.fourier = FourierEmbed(c.fourier_freqs)
        fe = self.fourier.out_per_vector
        self.text_mlp = mlp(dt, d)
        self.camera_mlp = mlp(7 * fe, d)
        self.lidar_token = nn.Parameter(torch.randn(d) * 0.02)
        self.ego_mlp = mlp(4 * fe, d)
        _, _, bev_c = cfg.sensors.bev.shape
        self.map_proj = nn.Linear(bev_c * c.map_patch**2, d)
        self.map_pos = nn.Parameter(torch.randn(cfg.map_tokens, d) * 0.02)
        self.box_mlp = mlp(8 * fe, d)
        self.category_proj = nn.Linear(dt, d)
        self.text_desc_proj = nn.Linear(dt, d)
        self.image_desc_proj = nn.Linear(di, d)
        self.null_text_desc = nn.Parameter(torch.randn(d) * 0.02)
        self.null_image_desc = nn.Parameter(torch.randn(d) * 0.02)
        self.object_mlp = mlp(4 * d, d)
        self.pad_object = nn.Parameter(torch.randn(d) * 0.02)
        self.null_text = nn.Parameter(torch.randn(d) * 0.02)
        self.null_control = nn.Parameter(torch.randn(d) * 0.02)

    def object_tokens(self, cond: Conditions) -> torch.Tensor:
        """(B, T, O, D); padding slots hold the pad token."""
        scale = self.cfg.control.position_scale_m
        box = self.box_mlp(self.fourier(cond.obj_corners / scale).flatten(-2))
        cat = self.category_proj(cond.obj_category)
        has_text, has_image = cond.obj_has_text, cond.obj_has_image
        if not self.cfg.control.object_descriptions:  # geometry-only baseline
            has_text, has_image = torch.zeros_like(has_text), torch.zeros_like(has_image)
        txt = torch.where(has_text[..., None], self.text_desc_proj(cond.obj_text), self.null_text_desc)
        img = torch.where(has_image[..., None], self.image_desc_proj(cond.obj_image), self.null_image_desc)
        tok = self.object_mlp(torch.cat([box, cat, img, txt], dim=-1))
        return torch.where(cond.obj_mask[..., None], tok, self.pad_object)

    def map_tokens(self, bev: torch.Tensor) -> torch.Tensor:
        """bev (B, T, h, w, c) -> (B, T, M, D)."""
        p = self.cfg.control.map_patch
        b, t, h, w, c = bev.shape
        x = bev.reshape(b, t, h // p, p, w // p, p, c).permute(0, 1, 2, 4, 3, 5, 6)
        return self.map_proj(x.reshape(b, t, (h // p) * (w // p), p * p * c)) + self.map_pos

    def forward(self, cond: Conditions) -> ControlTokens:
        b, t = cond.batch_size, cond.num_frames
        keep = ~cond.drop  # (B,)
        d = self.cfg.control.dim

        text = torch.cat([self.null_text.expand(b, 1, d), self.text_mlp(cond.text)], dim=1)
        text_mask = torch.cat(
            [torch.ones(b, 1, dtype=torch.bool, device=keep.device), cond.text_mask & keep[:, None]], dim=1
        )

        cam = cond.camera.clone()
        cam[..., 6, :] = cam[..., 6, :] / self.cfg.control.position_scale_m
        cam_tok = self.camera_mlp(self.fourier(cam).flatten(-2))  # (B, Vc, D)
        sensor = torch.cat([cam_tok, self.lidar_token.expand(b, 1, d)], dim=1)

        ego = cond.ego.clone()
        ego[..., 3, :] = ego[..., 3, :] / self.cfg.control.position_scale_m
        ego_tok = self.ego_mlp(self.fourier(ego).flatten(-2))[:, :, None]  # (B, T, 1, D)
        null = self.null_control.expand(b, t, 1, d)
        frame = torch.cat([ego_tok, self.map_tokens(cond.bev), self.object_tokens(cond), null], dim=2)
        ones = torch.ones(b, t, 1 + self.cfg.map_tokens, dtype=torch.bool, device=keep.device)
        frame_mask = torch.cat([ones, cond.obj_mask, torch.zeros_like(ones[..., :1])], dim=2)
        frame_mask = frame_mask & keep[:, None, None]
        frame_mask[..., -1] = True
        layout = cond.layout * keep[:, None, None, None, None, None].to(cond.layout.dtype)
        return ControlTokens(text, text_mask, sensor, frame, frame_mask, cond.view_adjacency, layout)
