"""The NumPy convolutions the torch-free runtime runs for a frame tokenizer equal torch's."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from hope_models.components.numpy_conv import Conv2d, ConvTranspose2d

CASES = [  # (torch layer, ours, cin, cout, kernel, stride, padding, input side)
    (torch.nn.Conv2d, Conv2d, 3, 16, 4, 2, 1, 64), (torch.nn.Conv2d, Conv2d, 16, 32, 3, 1, 1, 16),
    (torch.nn.Conv2d, Conv2d, 8, 8, 4, 2, 1, 96), (torch.nn.Conv2d, Conv2d, 5, 7, 3, 2, 0, 13),
    (torch.nn.ConvTranspose2d, ConvTranspose2d, 32, 16, 4, 2, 1, 4),
    (torch.nn.ConvTranspose2d, ConvTranspose2d, 16, 3, 4, 2, 1, 32),
    (torch.nn.ConvTranspose2d, ConvTranspose2d, 6, 5, 3, 2, 0, 7),
    (torch.nn.ConvTranspose2d, ConvTranspose2d, 4, 4, 3, 1, 1, 9),
]


@pytest.mark.parametrize("layer, ours, cin, cout, k, s, p, hw", CASES)
def test_numpy_convolutions_equal_torch(layer, ours, cin, cout, k, s, p, hw):
    torch.manual_seed(0)
    conv = layer(cin, cout, k, s, p)
    x = torch.randn(2, cin, hw, hw)
    want = conv(x).detach().numpy().transpose(0, 2, 3, 1)  # torch is NCHW, ours channels-last
    got = ours.from_torch(conv.weight.detach().numpy(), conv.bias.detach().numpy(), s, p)(x.numpy().transpose(0, 2, 3, 1))
    assert got.shape == want.shape and np.allclose(got, want, rtol=1e-4, atol=1e-5)
