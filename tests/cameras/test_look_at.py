"""The one `look_at`: a batch is its rows one by one, and looking straight along `up` still
gives a proper rotation (the target on the optical axis)."""

import torch

from recon.cameras.look_at import look_at

F64 = torch.float64


def test_a_batch_is_its_rows_one_by_one():
    gen = torch.Generator().manual_seed(0)
    eyes = torch.randn(5, 3, generator=gen, dtype=F64) * 3
    target, up = torch.tensor([0.1, 0.2, -0.3], dtype=F64), torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    batch = look_at(eyes, target, up)
    assert batch.shape == (5, 4, 4)
    for i in range(5):
        torch.testing.assert_close(batch[i], look_at(eyes[i], target, up), rtol=0, atol=1e-15)


def test_looking_along_up_is_still_a_rotation_with_the_target_ahead():
    eye, target = torch.tensor([0.0, 0.0, 2.0], dtype=F64), torch.zeros(3, dtype=F64)
    T = look_at(eye, target, torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    R = T[:3, :3]
    torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=F64))
    assert abs(float(torch.det(R)) - 1.0) < 1e-12
    in_camera = R @ target + T[:3, 3]
    torch.testing.assert_close(in_camera, torch.tensor([0.0, 0.0, 2.0], dtype=F64))
