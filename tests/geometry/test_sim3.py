import numpy as np
import torch

from endorecon.geometry import apply_sim3, so3_exp, umeyama


def test_umeyama_recovers_known_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3))
    R = so3_exp(torch.tensor([[0.3, -0.2, 1.1]], dtype=torch.float64))[0].numpy()
    dst = apply_sim3(0.37, R, np.array([1.0, 2.0, -3.0]), src)
    s, R2, t = umeyama(src, dst)
    assert abs(s - 0.37) < 1e-10
    assert np.allclose(R2, R) and np.allclose(t, [1, 2, -3])
    s_t, R_t, t_t = umeyama(torch.from_numpy(src), torch.from_numpy(dst))
    assert isinstance(R_t, torch.Tensor) and torch.allclose(R_t, torch.from_numpy(R))


def test_umeyama_rejects_bad_input():
    import pytest

    with pytest.raises(ValueError, match="at least 3"):
        umeyama(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        umeyama(np.full((4, 3), np.nan), np.zeros((4, 3)))


def test_umeyama_refuses_coincident_dst_instead_of_scale_zero():
    import pytest

    src = np.random.default_rng(0).normal(size=(6, 3))
    with pytest.raises(ValueError, match="dst points all coincide"):
        umeyama(src, np.tile([1.0, 2.0, 3.0], (6, 1)))
    with pytest.raises(ValueError, match="dst points all coincide"):  # a static reference with rounding jitter
        umeyama(src, np.tile([1.0, 2.0, 3.0], (6, 1)) + 1e-9 * np.random.default_rng(1).normal(size=(6, 3)))
    s, _, _ = umeyama(src, np.tile([1.0, 2.0, 3.0], (6, 1)), with_scale=False)  # rigid: still defined
    assert s == 1.0
