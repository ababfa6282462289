"""The NumPy convolutions the torch-free runtime runs for a frame tokenizer equal torch's."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from hope_models.components.numpy_conv import Conv2d, ConvTranspose2d


@pytest.mark.parametrize("cin, cout, k, s, p, hw", [(3, 16, 4, 2, 1, 64), (16, 32, 3, 1, 1, 16), (8, 8, 4, 2, 1, 96),
                                                     (5, 7, 3, 2, 0, 13)])
def test_conv2d_equals_torch(cin, cout, k, s, p, hw):
    torch.manual_seed(0)
    conv = torch.nn.Conv2d(cin, cout, k, s, p)
    x = torch.randn(2, cin, hw, hw)
    want = conv(x).detach().numpy().transpose(0, 2, 3, 1)
    ours = Conv2d.from_torch(conv.weight.detach().numpy(), conv.bias.detach().numpy(), s, p)
    got = ours(x.numpy().transpose(0, 2, 3, 1))
    assert got.shape == want.shape and np.allclose(got, want, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("cin, cout, k, s, p, hw", [(32, 16, 4, 2, 1, 4), (16, 3, 4, 2, 1, 32), (6, 5, 3, 2, 0, 7),
                                                     (4, 4, 3, 1, 1, 9)])
def test_conv_transpose2d_equals_torch(cin, cout, k, s, p, hw):
    torch.manual_seed(1)
    deconv = torch.nn.ConvTranspose2d(cin, cout, k, s, p)
    x = torch.randn(2, cin, hw, hw)
    want = deconv(x).detach().numpy().transpose(0, 2, 3, 1)
    ours = ConvTranspose2d.from_torch(deconv.weight.detach().numpy(), deconv.bias.detach().numpy(), s, p)
    got = ours(x.numpy().transpose(0, 2, 3, 1))
    assert got.shape == want.shape and np.allclose(got, want, rtol=1e-4, atol=1e-5)
