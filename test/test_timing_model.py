"""The timing network's shape, cost and ability to learn (``deepsync.timing.model``)."""

import dataclasses

import pytest

torch = pytest.importorskip("torch", reason="torch is not installed (scripts/setup.sh installs the CPU wheel)")

from deepsync.timing.model import Fusion, Head, TimingNet, TimingNetConfig, count_flops  # noqa: E402

CONFIG = TimingNetConfig()
EVERY_VARIANT = [TimingNetConfig(fusion=fusion, head=head) for fusion in Fusion for head in Head]
VARIANT_IDS = [f"{c.fusion.value}+{c.head.value}" for c in EVERY_VARIANT]


def inputs(batch: int, frames: int, seed: int = 0):
    generator = torch.Generator().manual_seed(seed)
    return (torch.randn(batch, frames, CONFIG.window_length, generator=generator),
            torch.randn(batch, CONFIG.template_length, generator=generator))


@pytest.mark.parametrize("batch, frames", [(1, 1), (3, 10), (2, 50)])
@pytest.mark.parametrize("config", EVERY_VARIANT, ids=VARIANT_IDS)
def test_any_number_of_frames_gives_an_offset_and_a_log_variance_per_cell(config, batch, frames):
    model = TimingNet(config).eval()
    offset, log_variance = model(*inputs(batch, frames))
    assert offset.shape == log_variance.shape == (batch,)
    assert torch.isfinite(offset).all() and torch.isfinite(log_variance).all()


def test_soft_argmax_puts_the_code_start_where_the_votes_point():
    """With every score but one token's far below, the offset is that token's vote: its position
    (a lag of ``pool`` samples per token) plus its correction, minus the margin."""
    config = TimingNetConfig(fusion=Fusion.CORRELATION, head=Head.SOFT_ARGMAX)
    model = TimingNet(config).eval()
    lags = config.fused_tokens
    assert lags == (config.window_length - config.template_length) // config.pool + 1
    for winner in (0, 4, lags - 1):
        scores = torch.full((lags,), -1e4)
        scores[winner] = 0.0
        model.fuse = lambda signal, code, scores=scores: torch.stack(
            [scores, torch.full_like(scores, 0.25)], dim=-1).expand(signal.shape[0], -1, -1)
        model.votes = torch.nn.Identity()
        model.regression = torch.nn.Sequential(torch.nn.Flatten(), torch.nn.Linear(2 * lags, config.hidden[-1]))
        with torch.no_grad():
            offset, _ = model(*inputs(2, 3))
        margin = (config.window_length - config.template_length) / 2
        torch.testing.assert_close(offset, torch.full((2,), winner * config.pool + 0.25 - margin))


@pytest.mark.parametrize("config", EVERY_VARIANT, ids=VARIANT_IDS)
def test_the_frames_are_aggregated_whatever_their_order(config):
    model = TimingNet(config).eval()
    windows, template = inputs(2, 10)
    with torch.no_grad():
        a = model(windows, template)
        b = model(windows[:, torch.randperm(10)], template)
    torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("config", EVERY_VARIANT, ids=VARIANT_IDS)
def test_the_cells_of_a_batch_do_not_mix(config):
    model = TimingNet(config).eval()
    windows, template = inputs(4, 10)
    with torch.no_grad():
        together = model(windows, template)[0]
        alone = torch.cat([model(windows[i : i + 1], template[i : i + 1])[0] for i in range(4)])
    torch.testing.assert_close(together, alone, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("config", EVERY_VARIANT, ids=VARIANT_IDS)
def test_one_inference_costs_at_most_the_papers_46_mflops(config):
    model = TimingNet(config)
    flops = count_flops(model, frames=10)
    assert 1e6 < flops <= 46e6
    assert count_flops(model, frames=20) > flops  # each frame goes through the encoder
    assert model.training  # the count leaves the model as it found it


@pytest.mark.parametrize("change, field", [
    (dict(channels=(8, 16, 30)), "heads"),
    (dict(template_length=400), "template_length"),
    (dict(pool=0), "pool"),
    (dict(dropout=1.0), "dropout"),
    (dict(kernels=(14, 7)), "kernels"),
    (dict(fusion="sum"), "fusion"),
    (dict(head="argmax"), "head"),
])
def test_a_config_that_cannot_be_built_names_the_field(change, field):
    with pytest.raises(ValueError, match=field):
        dataclasses.replace(CONFIG, **change)


def test_a_choice_given_by_name_is_the_choice():
    config = TimingNetConfig(fusion="correlation", head="soft_argmax")
    assert (config.fusion, config.head) == (Fusion.CORRELATION, Head.SOFT_ARGMAX)
    assert config == TimingNetConfig(fusion=Fusion.CORRELATION, head=Head.SOFT_ARGMAX)


@pytest.mark.parametrize("config", [TimingNetConfig(fusion=fusion) for fusion in Fusion]
                         + [TimingNetConfig(fusion=fusion, head=Head.SOFT_ARGMAX)
                            for fusion in (Fusion.CROSS_ATTENTION, Fusion.CORRELATION)],
                         ids=lambda c: f"{c.fusion.value}+{c.head.value}")
def test_it_learns_where_the_template_sits_in_the_windows(config):
    """A seconds-long smoke training on a task with a known answer: noisy windows holding the
    template at a random offset; the Huber loss must fall well below guessing the mean."""
    torch.manual_seed(0)
    model = TimingNet(config)
    optimiser = torch.optim.Adam(model.parameters(), lr=3e-3)
    margin = (CONFIG.window_length - CONFIG.template_length) // 2  # the offset's zero
    template = torch.zeros(CONFIG.template_length)
    template[40:60], template[150:170] = 1.0, -1.0  # two pulses: a code-like shape with one alignment

    def batch(size: int):
        offsets = torch.randint(-margin, margin + 1, (size,))
        windows = 0.3 * torch.randn(size, 4, CONFIG.window_length)
        for i, offset in enumerate(offsets.tolist()):
            windows[i, :, margin + offset : margin + offset + CONFIG.template_length] += template
        return windows, template.expand(size, -1), offsets.float()

    loss = torch.nn.HuberLoss(delta=1.0)
    windows, templates, truth = batch(64)
    with torch.no_grad():
        guessing = loss(torch.full_like(truth, truth.mean().item()), truth).item()
    for _ in range(60):
        w, t, y = batch(32)
        offset, _ = model(w, t)
        optimiser.zero_grad()
        loss(offset, y).backward()
        optimiser.step()
    model.eval()
    with torch.no_grad():
        trained = loss(model(windows, templates)[0], truth).item()
    assert trained < 0.3 * guessing, (trained, guessing)
