"""Standard LPIPS-Alex from the user's two weight files (torchvision AlexNet + lpips alex.pth)."""

import pytest
import torch
from torch import nn

from delta.perceptual.nets import AlexNet, lpips_alex_state
from delta.perceptual.stlpips import lpips_alex


def torchvision_like_alexnet(path, seed=0):
    """A file with torchvision's AlexNet key names and shapes (random weights; the classifier too)."""
    g = torch.Generator().manual_seed(seed)
    shapes = {0: (64, 3, 11, 11), 3: (192, 64, 5, 5), 6: (384, 192, 3, 3), 8: (256, 384, 3, 3), 10: (256, 256, 3, 3)}
    state = {}
    for i, s in shapes.items():
        state[f"features.{i}.weight"] = torch.randn(s, generator=g) * (2 / (s[1] * s[2] * s[3])) ** 0.5
        state[f"features.{i}.bias"] = torch.zeros(s[0])
    state["classifier.1.weight"] = torch.zeros(4, 9216)
    torch.save(state, path)


def lpips_lin(path, seed=1):
    g = torch.Generator().manual_seed(seed)
    state = {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) for k, c in enumerate(AlexNet.channels)}
    torch.save(state, path)


@pytest.fixture
def files(tmp_path):
    torchvision_like_alexnet(tmp_path / "alexnet.pth")
    lpips_lin(tmp_path / "alex.pth")
    return tmp_path / "alexnet.pth", tmp_path / "alex.pth"


def test_the_trunk_is_torchvision_alexnet(files):
    """Feature sizes of torchvision's AlexNet at 224²: 55, 27, 13, 13, 13 (stride-4 first conv)."""
    net = AlexNet()
    feats = net(torch.rand(1, 3, 224, 224))
    assert [f.shape[-1] for f in feats] == [55, 27, 13, 13, 13]
    assert [f.shape[1] for f in feats] == list(AlexNet.channels)
    # every torchvision key lands on the matching layer
    state = lpips_alex_state(*files)
    trunk = torch.load(files[0], weights_only=True)
    net.load_state_dict({k[4:]: v for k, v in state.items() if k.startswith("net.")})
    assert torch.equal(getattr(net.slice3, "6").weight, trunk["features.6.weight"])
    assert isinstance(getattr(net.slice2, "2"), nn.MaxPool2d) and getattr(net.slice1, "0").stride == (4, 4)


def test_distance_is_zero_for_identical_images_and_grows_with_noise(files):
    metric = lpips_alex(*files)
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1, 3, 64, 64, generator=g)
    d = [float(metric(x, (x + s * torch.randn(x.shape, generator=g)).clamp(0, 1))) for s in (0.0, 0.05, 0.3)]
    assert d[0] == 0.0 and 0 < d[1] < d[2]


def test_wrong_files_are_named(tmp_path, files):
    torch.save({"features.0.weight": torch.zeros(1)}, tmp_path / "partial.pth")
    with pytest.raises(KeyError, match="partial.pth.*features.0.bias"):
        lpips_alex_state(tmp_path / "partial.pth", files[1])
    with pytest.raises(KeyError, match="lin0.model.1.weight"):
        lpips_alex_state(files[0], files[0])
