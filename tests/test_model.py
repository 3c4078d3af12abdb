"""The Roken DiT, its loss and samplers: symmetry, masks, log-probabilities, caching, and that it learns."""
import math

import numpy as np
import pytest
import torch
from scipy.stats import norm

from roken.data.loader import ChunkDataset, collate
from roken.data.samples import EpisodeBank, SampleConfig
from roken.model.diffusion import (COND_KEYS, DiffusionConfig, NoiseSchedule, ddim_sample, ddpm_sample, make_prompt,
                                   transition_logprob)
from roken.model.dit import RokenDiT, preset
from roken.model.losses import LossConfig, pretraining_loss, sdf_at
from roken.world.geometry import bilinear


def randomized(cfg) -> RokenDiT:
    """A model whose zero-initialised AdaLN / output weights are made random, so every path is exercised."""
    torch.manual_seed(0)
    m = RokenDiT(cfg)
    with torch.no_grad():
        for p in m.parameters():
            if (p == 0).all():
                p.normal_(0, 0.05)
    return m.eval()


@pytest.fixture(scope="module")
def batch(expert_dataset):
    ds = ChunkDataset(EpisodeBank.from_folder(expert_dataset), SampleConfig(condition_prob=0.5), seed=1)
    return collate([ds[k] for k in range(6)])


def cond_of(batch):
    return {k: batch[k] for k in COND_KEYS + ("map",)}


def test_paper_preset_has_the_papers_parameter_count():
    n = RokenDiT(preset("paper")).num_params()
    assert abs(n - 11.9e6) / 11.9e6 < 0.03, n
    assert RokenDiT(preset("tiny")).num_params() < 0.5e6
    # The switch for AdaLN-Zero's gate on the cross-attention output adds one modulation vector per layer.
    gated = RokenDiT(preset("paper", cross_attn_gate=True)).num_params()
    assert gated - n == 8 * (256 * 256 + 256)


def test_robot_permutation_equivariance(batch):
    model = randomized(preset("tiny"))
    k = torch.tensor([3, 50, 99, 10, 0, 70])
    x = torch.randn(batch["chunk"].shape)
    perm = torch.randperm(10)
    permuted = {key: (v[:, perm] if key in COND_KEYS else v) for key, v in cond_of(batch).items()}
    with torch.no_grad():
        a = model(x, k, cond_of(batch), aux=True)
        b = model(x[:, perm], k, permuted, aux=True)
    real = batch["robot_mask"][:, perm]
    for key in ("eps", "waypoints", "occ_small", "occ_large"):
        torch.testing.assert_close(a[key][:, perm][real], b[key][real], atol=2e-5, rtol=1e-4)


def test_padding_tokens_change_nothing(batch):
    model = randomized(preset("tiny"))
    i = int(torch.argmin(batch["num_robots"]))  # fewest robots: most padding
    N = int(batch["num_robots"][i])
    cond = {key: v[i:i + 1] for key, v in cond_of(batch).items()}
    x = torch.randn(1, 10, 16, 2)
    k = torch.tensor([40])
    with torch.no_grad():
        full = model(x, k, cond, aux=True)
        junk = {key: (v.clone() if key in COND_KEYS else v) for key, v in cond.items()}
        junk["start"][:, N:] = torch.rand(1, 10 - N, 2) * 140
        junk["rel_goal"][:, N:] = torch.randn(1, 10 - N, 2)
        junk["goal_mask"][:, N:] = 1
        x2 = x.clone()
        x2[:, N:] = torch.randn(1, 10 - N, 16, 2) * 5
        noisy = model(x2, k, junk, aux=True)
        short = model(x[:, :N], k, {key: (v[:, :N] if key in COND_KEYS else v) for key, v in cond.items()}, aux=True)
    for key in ("eps", "waypoints", "occ_small"):
        torch.testing.assert_close(noisy[key][:, :N], full[key][:, :N], atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(short[key], full[key][:, :N], atol=1e-5, rtol=1e-5)


def test_candidates_share_one_map_encoding_and_match_explicit_copies(batch):
    model = randomized(preset("tiny"))
    cond = cond_of(batch)
    calls = []
    model.map_encoder.register_forward_hook(lambda *a: calls.append(1))
    prompt = make_prompt(model, cond, num_candidates=4)
    x = torch.randn(24, 10, 16, 2)
    k = torch.randint(0, 100, (24,))
    with torch.no_grad():
        grouped = model(x, k, prompt.cond, ctx=prompt.ctx)["eps"]
        explicit = model(x, k, {**prompt.cond, "map": cond["map"].repeat_interleave(4, 0)})["eps"]
    torch.testing.assert_close(grouped, explicit, atol=1e-5, rtol=1e-5)
    calls.clear()
    ddim_sample(model, NoiseSchedule(DiffusionConfig()), make_prompt(model, cond, num_candidates=8), steps=10)
    assert len(calls) == 1, "the map is encoded once per plan, not once per denoising step or candidate"


@pytest.mark.parametrize("sampler", ["ddpm", "ddim"])
def test_conditioned_robots_are_returned_exactly(batch, sampler):
    model = randomized(preset("tiny"))
    sched = NoiseSchedule(DiffusionConfig(num_steps=20))
    cond = cond_of(batch)
    assert batch["traj_mask"].sum() > 0
    prompt = make_prompt(model, cond, given=batch["chunk"], num_candidates=3)
    gen = torch.Generator().manual_seed(0)
    out = (ddpm_sample(model, sched, prompt, generator=gen) if sampler == "ddpm"
           else ddim_sample(model, sched, prompt, steps=5, eta=0.5, generator=gen)).chunk
    fixed = prompt.fixed.expand_as(out)
    assert torch.equal(out[fixed], prompt.given[fixed])
    assert not torch.allclose(out[~fixed], prompt.given[~fixed])
    # The 3 candidates of a prompt differ (independent noise) where robots are generated.
    gen_rows = prompt.generated[0].bool()
    assert not torch.allclose(out[0][gen_rows], out[1][gen_rows])


def test_ddpm_logprob_is_the_gaussian_density_of_each_transition(batch):
    model = randomized(preset("tiny"))
    sched = NoiseSchedule(DiffusionConfig(num_steps=12))
    prompt = make_prompt(model, cond_of(batch), given=batch["chunk"], num_candidates=2)
    r = ddpm_sample(model, sched, prompt, generator=torch.Generator().manual_seed(1), record=True)
    assert r.latents.shape[0] == 13 and r.logprobs.shape == (12, 12) and torch.equal(r.latents[-1], r.chunk)
    mask = prompt.generated.bool().numpy()
    for s in (0, 5, 11):
        x, mu, sd = r.latents[s + 1].double().numpy(), r.means[s].double().numpy(), float(r.sigmas[s])
        direct = np.array([norm.logpdf(x[b][mask[b]], mu[b][mask[b]], sd).sum() for b in range(len(x))])
        np.testing.assert_allclose(r.logprobs[s].numpy(), direct, rtol=1e-4, atol=1e-2)
        # GRPO recomputes the same log-probability from (x_k, x_{k-1}) with the current weights.
        k = r.steps[s].repeat(len(x))
        again = transition_logprob(model, sched, prompt, r.latents[s], k, r.latents[s + 1])
        torch.testing.assert_close(again.detach(), r.logprobs[s], rtol=1e-4, atol=1e-2)
    assert torch.isfinite(r.logprobs).all() and (r.sigmas > 0).all()


def test_sdf_lookup_matches_the_world_bilinear_and_is_differentiable():
    rng = np.random.default_rng(0)
    field = rng.normal(size=(2, 140, 140)).astype(np.float32)
    pts = rng.uniform(0.6, 139.4, size=(2, 50, 2)).astype(np.float32)
    want, grad = bilinear(field, pts, np.repeat([[0], [1]], 50, axis=1), with_grad=True)
    p = torch.tensor(pts, requires_grad=True)
    got = sdf_at(torch.tensor(field), p)
    np.testing.assert_allclose(got.detach().numpy(), want, atol=1e-4)
    got.sum().backward()
    np.testing.assert_allclose(p.grad.numpy(), grad, atol=1e-3)


def test_loss_terms_switch_off_and_absolute_representation_runs(batch):
    model = RokenDiT(preset("tiny"))
    sched = NoiseSchedule(DiffusionConfig())
    _, m = pretraining_loss(model, sched, batch, LossConfig(), SampleConfig())
    assert set(m) == {"losses/traj", "losses/wp", "losses/occ", "losses/sdf", "losses/total"}
    loss, m = pretraining_loss(model, sched, batch, LossConfig(wp=0, occ=0, sdf=0), SampleConfig())
    assert set(m) == {"losses/traj", "losses/total"} and torch.isfinite(loss)
    loss, _ = pretraining_loss(model, sched, batch, LossConfig(), SampleConfig(representation="absolute"))
    loss.backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


@pytest.mark.parametrize("prediction", ["eps", "v", "x0"])
def test_every_parametrisation_gives_back_the_noise_and_weights_the_eps_loss_as_documented(prediction):
    """diffusion.prediction: the target of a (x0, eps, k) draw reads back as eps and as x0; an output's squared
    error in its own parametrisation is the eps error times 1 (eps), 1 / abar (v) or (1 - abar) / abar (x0)."""
    sched = NoiseSchedule(DiffusionConfig(num_steps=100, prediction=prediction, clip_sample=0))
    g = torch.Generator().manual_seed(0)
    x0, eps = torch.randn(8, 4, 16, 2, generator=g), torch.randn(8, 4, 16, 2, generator=g)
    k = torch.tensor([0, 1, 10, 40, 70, 90, 98, 99])
    xk = sched.q_sample(x0, k, eps)
    back = sched.eps_from(sched.target(x0, eps, k), xk, k)
    torch.testing.assert_close(back, eps, atol=2e-3, rtol=1e-3)
    torch.testing.assert_close(sched.predict_x0(xk[:6], k[:6], back[:6]), x0[:6], atol=2e-3, rtol=1e-3)
    out = sched.target(x0, eps, k) + 0.1 * torch.randn(x0.shape, generator=g)  # an imperfect denoiser
    own = ((out - sched.target(x0, eps, k)) ** 2).mean(dim=(1, 2, 3))
    in_eps = ((sched.eps_from(out, xk, k) - eps) ** 2).mean(dim=(1, 2, 3))
    a = sched.abar[k].double()
    weight = {"eps": torch.ones_like(a), "v": 1 / a, "x0": (1 - a) / a}[prediction]
    torch.testing.assert_close(own.double(), in_eps.double() * weight, rtol=2e-3, atol=1e-6)
    with pytest.raises(ValueError, match="diffusion.prediction must be one of eps, v, x0"):
        NoiseSchedule(DiffusionConfig(prediction="sample"))


@pytest.mark.parametrize("prediction", ["eps", "v", "x0"])
def test_small_model_overfits_a_handful_of_samples_and_samples_them_back(batch, prediction):
    """Loss on 4 fixed samples falls by a large factor, and then DDPM samples land close to their chunks, in
    every parametrisation of the denoiser (diffusion.prediction)."""
    torch.manual_seed(0)
    few = {k: v[:4] for k, v in batch.items()}
    few["traj_mask"] = torch.zeros_like(few["traj_mask"])
    model = RokenDiT(preset("tiny"))
    sched = NoiseSchedule(DiffusionConfig(num_steps=50, prediction=prediction))
    cfg = LossConfig(sdf=0.0)  # L_sdf pulls away from the expert inside 4 m of walls; it has its own test
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3)

    def loss_now():
        with torch.no_grad():
            return float(np.mean([float(pretraining_loss(model, sched, few, cfg, SampleConfig(),
                                                         torch.Generator().manual_seed(s))[0]) for s in range(8)]))

    def sample_error():
        model.eval()
        prompt = make_prompt(model, cond_of(few))
        out = ddpm_sample(model, sched, prompt, generator=torch.Generator().manual_seed(0)).chunk
        model.train()
        real = few["robot_mask"]
        return float((out - few["chunk"]).norm(dim=-1)[real].mean())

    before, err_before = loss_now(), sample_error()
    for _ in range(500):
        loss, _ = pretraining_loss(model, sched, few, cfg, SampleConfig())
        opt.zero_grad()
        loss.backward()
        opt.step()
    after, err_after = loss_now(), sample_error()
    assert after < before / 8, (before, after)
    assert err_after < 0.35 * err_before, (err_before, err_after)
    assert math.isfinite(after)
