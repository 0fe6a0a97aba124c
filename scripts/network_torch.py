#!/usr/bin/env python3
"""The official PoseDiffusion network timed in PyTorch (`cargo xtask bench-network`, `scripts/device_check.sh`).

The modules are the official ones written out: DINO's `vision_transformer.py` (ViT-S/16, the
`Attention`/`Mlp`/`Block` of facebookresearch/dino @ 7c446df, positional-embedding interpolation
included), the `MultiScaleImageFeatureExtractor` of PoseDiffusion (scales 1, 1/2, 1/3, bilinear
with the scale-factor mapping), and its `Denoiser` (time and harmonic pose embeddings,
`nn.TransformerEncoder` pre-LN with PyTorch's inference fast path, the `_last` MLP) with the
DDPM `p_sample_loop` (100 steps, no GGS). SPEC.md §3-4 describes them; the weights are the
random-weight checkpoint of `shared/reference/full` in the official key layout. Before timing,
the script checks itself against the official outputs of `denoiser_io.safetensors` (features
and a denoiser step), so what is timed is the official network. Given `--reference` a `tiny`
fixture folder instead (2 ViT blocks, 2 trunk layers: what travels to a GPU machine), it
checks itself on the tiny model and times an official-size network with PyTorch's default
initialisation (the timings do not depend on the weights). `--device cuda` times on the GPU
(synchronised); `--train-iterations K` also times K iterations of the official training step
with a frozen backbone (`train.py`: ⌊512 / 50⌋ = 10 sets of 50 frames, batch repeat 90, the L1
noise loss, gradient clipping at 1, AdamW), as `posediff device-check` does.

    python scripts/network_torch.py --reference ../shared/reference/full --frames 10,20,100 \
        --threads 2 --out target/bench-network/pytorch.json
"""

import argparse
import json
import math
import struct
import time

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

DTYPES = {"F16": np.float16, "F32": np.float32, "F64": np.float64, "I64": np.int64}


def read_safetensors(path):
    """A safetensors file as float32/int64 torch tensors (no safetensors package needed)."""
    with open(path, "rb") as f:
        (n,) = struct.unpack("<Q", f.read(8))
        header = json.loads(f.read(n))
        data = f.read()
    out = {}
    for key, meta in header.items():
        if key == "__metadata__":
            continue
        a, b = meta["data_offsets"]
        arr = np.frombuffer(data[a:b], dtype=DTYPES[meta["dtype"]]).reshape(meta["shape"])
        arr = arr.astype(np.int64 if meta["dtype"] == "I64" else np.float32)
        out[key] = torch.from_numpy(arr.copy())
    return out


# ---------------------------------------------------------------- DINO ViT-S/16 (dino @ 7c446df)
class Mlp(nn.Module):
    def __init__(self, dim, hidden):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x):
        return self.fc2(self.act(self.fc1(x)))


class Attention(nn.Module):
    def __init__(self, dim, heads):
        super().__init__()
        self.num_heads = heads
        self.scale = (dim // heads) ** -0.5
        self.qkv = nn.Linear(dim, dim * 3, bias=True)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x):
        B, N, C = x.shape
        qkv = self.qkv(x).reshape(B, N, 3, self.num_heads, C // self.num_heads).permute(2, 0, 3, 1, 4)
        q, k, v = qkv[0], qkv[1], qkv[2]
        attn = (q @ k.transpose(-2, -1)) * self.scale
        attn = attn.softmax(dim=-1)
        x = (attn @ v).transpose(1, 2).reshape(B, N, C)
        return self.proj(x)


class Block(nn.Module):
    def __init__(self, dim, heads):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = Attention(dim, heads)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = Mlp(dim, dim * 4)

    def forward(self, x):
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))


class PatchEmbed(nn.Module):
    def __init__(self, dim):
        super().__init__()
        self.proj = nn.Conv2d(3, dim, kernel_size=16, stride=16)

    def forward(self, x):
        return self.proj(x).flatten(2).transpose(1, 2)


class VisionTransformer(nn.Module):
    def __init__(self, dim=384, depth=12, heads=6):
        super().__init__()
        self.patch_size = 16
        self.patch_embed = PatchEmbed(dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, 197, dim))
        self.blocks = nn.ModuleList([Block(dim, heads) for _ in range(depth)])
        self.norm = nn.LayerNorm(dim, eps=1e-6)

    def interpolate_pos_encoding(self, x, w, h):
        npatch = x.shape[1] - 1
        N = self.pos_embed.shape[1] - 1
        if npatch == N and w == h:
            return self.pos_embed
        class_pos_embed = self.pos_embed[:, 0]
        patch_pos_embed = self.pos_embed[:, 1:]
        dim = x.shape[-1]
        w0 = w // self.patch_size
        h0 = h // self.patch_size
        w0, h0 = w0 + 0.1, h0 + 0.1
        patch_pos_embed = F.interpolate(
            patch_pos_embed.reshape(1, int(math.sqrt(N)), int(math.sqrt(N)), dim).permute(0, 3, 1, 2),
            scale_factor=(w0 / math.sqrt(N), h0 / math.sqrt(N)),
            mode="bicubic",
        )
        patch_pos_embed = patch_pos_embed.permute(0, 2, 3, 1).view(1, -1, dim)
        return torch.cat((class_pos_embed.unsqueeze(0), patch_pos_embed), dim=1)

    def forward(self, x):
        B, _, w, h = x.shape
        x = self.patch_embed(x)
        x = torch.cat((self.cls_token.expand(B, -1, -1), x), dim=1)
        x = x + self.interpolate_pos_encoding(x, w, h)
        for blk in self.blocks:
            x = blk(x)
        return self.norm(x)[:, 0]


class MultiScaleImageFeatureExtractor(nn.Module):
    def __init__(self, depth=12):
        super().__init__()
        self._net = VisionTransformer(depth=depth)
        self.register_buffer("_resnet_mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("_resnet_std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1), persistent=False)
        self.scale_factors = [1, 1 / 2, 1 / 3]

    def forward(self, image_rgb):
        img_normed = (image_rgb - self._resnet_mean) / self._resnet_std
        feats = []
        for scale_factor in self.scale_factors:
            if scale_factor == 1:
                inp = img_normed
            else:
                inp = F.interpolate(img_normed, scale_factor=scale_factor, mode="bilinear", align_corners=False)
            feats.append(self._net(inp))
        return sum(feats) / len(feats)


# ---------------------------------------------------------------- the denoiser (denoiser.py)
class TimeStepEmbedding(nn.Module):
    def __init__(self, dim=256, max_period=10000):
        super().__init__()
        self.dim = dim
        self.max_period = max_period
        self.linear = nn.Sequential(nn.Linear(dim, dim // 2), nn.SiLU(), nn.Linear(dim // 2, dim // 2))

    def forward(self, timesteps):
        half = self.dim // 2
        freqs = torch.exp(
            -math.log(self.max_period) * torch.arange(0, half, dtype=torch.float32, device=timesteps.device) / half
        )
        args = timesteps[:, None].float() * freqs[None]
        return self.linear(torch.cat([torch.cos(args), torch.sin(args)], dim=-1))


class PoseEmbedding(nn.Module):
    """pytorch3d 0.7.4 HarmonicEmbedding(10, omega_0=1, logspace, append_input)."""

    def __init__(self):
        super().__init__()
        self.register_buffer("_frequencies", 2.0 ** torch.arange(10, dtype=torch.float32), persistent=False)

    def forward(self, x):
        embed = (x[..., None] * self._frequencies).reshape(*x.shape[:-1], -1)
        return torch.cat((embed.sin(), embed.cos(), x), dim=-1)


class MLPHead(nn.Sequential):
    def __init__(self):
        super().__init__(nn.Linear(512, 128), nn.LayerNorm(128), nn.ReLU(), nn.Linear(128, 9))


class Denoiser(nn.Module):
    def __init__(self, layers=8):
        super().__init__()
        self.time_embed = TimeStepEmbedding()
        self.pose_embed = PoseEmbedding()
        self._first = nn.Linear(189 + 128 + 384 + 1, 512)
        layer = nn.TransformerEncoderLayer(
            d_model=512, nhead=4, dim_feedforward=1024, dropout=0.1, activation="relu",
            batch_first=True, norm_first=True, layer_norm_eps=1e-5,
        )
        self._trunk = nn.TransformerEncoder(layer, num_layers=layers, enable_nested_tensor=False)
        self._last = MLPHead()

    def forward(self, x, t, z):
        B, N, _ = z.shape
        pivot = torch.zeros(B, N, 1, device=z.device)
        pivot[:, 0] = 1
        z = torch.cat([z, pivot], dim=-1)
        t_emb = self.time_embed(t).view(B, 1, -1).expand(-1, N, -1)
        feed = torch.cat([self.pose_embed(x), t_emb, z], dim=-1)
        return self._last(self._trunk(self._first(feed)))


def p_sample_loop(denoiser, sched, z, gen):
    B, N, _ = z.shape
    x = torch.randn(B, N, 9, generator=gen, device=z.device)
    for t in reversed(range(100)):
        tt = torch.full((B,), t, dtype=torch.long, device=z.device)
        eps = denoiser(x, tt, z)
        x0 = sched["sqrt_recip_alphas_cumprod"][t] * x - sched["sqrt_recipm1_alphas_cumprod"][t] * eps
        mean = sched["posterior_mean_coef1"][t] * x0 + sched["posterior_mean_coef2"][t] * x
        noise = torch.randn(x.shape, generator=gen, device=x.device) if t > 0 else torch.zeros_like(x)
        x = mean + (0.5 * sched["posterior_log_variance_clipped"][t]).exp() * noise
    return x


def fixture_files(reference):
    """The model and the denoiser outputs of a fixture folder (full or tiny)."""
    import os

    if os.path.isfile(f"{reference}/model_random.safetensors"):
        return f"{reference}/model_random.safetensors", f"{reference}/denoiser_io.safetensors", True
    return f"{reference}/model_tiny.safetensors", f"{reference}/denoiser_io_tiny.safetensors", False


def load(model_path, device):
    """The network of a checkpoint in the official key layout (depths read from its keys)."""
    if model_path.endswith(".pth"):
        # A state dict saved by torch (possibly under `module.`, as DDP saves it).
        raw = torch.load(model_path, map_location="cpu", weights_only=True)
        state = {k.removeprefix("module."): v.float() for k, v in raw.items()}
    else:
        state = read_safetensors(model_path)
    pre_e, pre_d = "image_feature_extractor.", "diffuser.model."
    blocks = {int(k.split(".")[3]) for k in state if k.startswith(pre_e + "_net.blocks.")}
    layers = {int(k.split(".")[4]) for k in state if k.startswith(pre_d + "_trunk.layers.")}
    extractor = MultiScaleImageFeatureExtractor(depth=len(blocks))
    denoiser = Denoiser(layers=len(layers))
    extractor.load_state_dict({k[len(pre_e):]: v for k, v in state.items() if k.startswith(pre_e)})
    denoiser.load_state_dict({k[len(pre_d):]: v for k, v in state.items() if k.startswith(pre_d)})
    sched = {
        k[len("diffuser."):]: v.to(device)
        for k, v in state.items()
        if k.startswith("diffuser.") and not k.startswith(pre_d)
    }
    return extractor.to(device).eval(), denoiser.to(device).eval(), sched


def check(extractor, denoiser, io_path, device):
    """Max abs differences against the official outputs of a denoiser_io file."""
    io = {k: v.to(device) for k, v in read_safetensors(io_path).items()}
    feats = extractor(io["images"])
    out = denoiser(io["x_t"], torch.tensor([37], device=device), io["z"])
    return {
        "features_max_abs": float((feats - io["features"]).abs().max()),
        "denoiser_t37_max_abs": float((out - io["out_t37"]).abs().max()),
    }


def best_of(fn, repeats, device):
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    return min(times), times


def train_rate(denoiser, sched, device, iterations, sets=10, frames=50, repeat=90):
    """Seconds per official training iteration with a frozen backbone (features given)."""
    denoiser.train()
    params = [p for p in denoiser.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=1e-4)
    b = sets * repeat
    z = torch.randn(sets, frames, 384, device=device).repeat(repeat, 1, 1)
    x0 = torch.randn(sets, frames, 9, device=device).repeat(repeat, 1, 1)
    a, s1 = sched["sqrt_alphas_cumprod"], sched["sqrt_one_minus_alphas_cumprod"]
    seconds = []
    for i in range(iterations + 1):
        if device.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        t = torch.randint(0, 100, (b,), device=device)
        noise = torch.randn(b, frames, 9, device=device)
        x_t = a[t].view(b, 1, 1) * x0 + s1[t].view(b, 1, 1) * noise
        loss = (denoiser(x_t, t, z) - noise).abs().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        float(loss.detach())
        if device.type == "cuda":
            torch.cuda.synchronize()
        if i > 0:
            seconds.append(time.perf_counter() - start)
    denoiser.eval()
    mean = sum(seconds) / max(len(seconds), 1)
    return {"preset": "official", "sets": sets, "frames": frames, "batch_repeat": repeat,
            "seconds_per_iteration": mean, "iterations_per_s": 1.0 / mean, "loss": float(loss.detach())}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reference", required=True)
    ap.add_argument("--model", help="the fixtures' model when not in --reference (safetensors or .pth)")
    ap.add_argument("--frames", default="10,20,100")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--train-iterations", type=int, default=0)
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    device = torch.device(args.device)
    if device.type == "cuda":
        # Full float32 products, as posediff device-check runs them.
        torch.backends.cuda.matmul.allow_tf32 = False
        torch.backends.cudnn.allow_tf32 = False
    model_path, io_path, full_size = fixture_files(args.reference)
    model_path = args.model or model_path
    # Built outside inference mode: the training step needs ordinary parameters.
    extractor, denoiser, sched = load(model_path, device)
    with torch.inference_mode():
        checks = check(extractor, denoiser, io_path, device)
        if checks["features_max_abs"] > 1e-4 or checks["denoiser_t37_max_abs"] > 1e-4:
            raise SystemExit(f"the PyTorch network does not reproduce the official outputs: {checks}")
    if not full_size:
        # Official size, PyTorch's default initialisation (the tiny model was only checked).
        extractor = MultiScaleImageFeatureExtractor().to(device).eval()
        denoiser = Denoiser().to(device).eval()
    with torch.inference_mode():
        rows = []
        gen = torch.Generator(device=device).manual_seed(0)
        for n in [int(s) for s in args.frames.split(",")]:
            images = torch.rand(n, 3, 224, 224, generator=gen, device=device)
            extractor(images)  # warm-up
            feat_s, feat_all = best_of(lambda: extractor(images), args.repeats, device)
            z = extractor(images).view(1, n, 384)
            x = torch.randn(1, n, 9, device=device)
            t50 = torch.tensor([50], device=device)
            denoiser(x, t50, z)
            step_s, _ = best_of(lambda: denoiser(x, t50, z), 10, device)
            sample_s, sample_all = best_of(lambda: p_sample_loop(denoiser, sched, z, gen), args.repeats, device)
            rows.append({
                "frames": n,
                "features_s": feat_s,
                "features_runs_s": feat_all,
                "denoiser_step_s": step_s,
                "sampling_100_s": sample_s,
                "sampling_runs_s": sample_all,
            })
            print(f"pytorch {n} frames: features {feat_s:.4f} s, 100 steps {sample_s:.4f} s", flush=True)
    training = None
    if args.train_iterations > 0:
        try:
            training = train_rate(denoiser, sched, device, args.train_iterations)
        except RuntimeError as e:  # out of memory, say: the forward timings still count
            training = {"preset": "official", "error": str(e).splitlines()[0]}
    report = {
        "torch": torch.__version__,
        "device": args.device,
        "threads": args.threads,
        "checked_on": model_path,
        "timed": model_path if full_size else "official size, PyTorch default initialisation",
        "checks": checks,
        "rows": rows,
        "training": training,
    }
    with open(args.out, "w") as f:
        json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
