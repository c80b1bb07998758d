"""as_numpy: torch tensors and arrays alike as numpy arrays of a dtype (no torch in the module)."""
import numpy as np
import torch

from metampc_model.arrays import as_numpy


def test_tensors_with_a_gradient_and_arrays_become_arrays_rounded_as_torch_rounds():
    values = torch.randn(3, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    grad = values.clone().requires_grad_(True)
    want = values.to(torch.float32).numpy()
    for value in (values, grad, values.numpy(), values.tolist()):
        got = as_numpy(value, np.float32)
        assert got.dtype == np.float32 and got.shape == (3, 4)
        assert np.array_equal(got, want)
    assert np.array_equal(as_numpy(values.to(torch.float32), np.float64), want.astype(np.float64))
