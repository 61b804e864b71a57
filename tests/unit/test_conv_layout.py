"""The conv torso reads frame stacks [k, H, W] channels first and images [H, W, C] channels
last: the same weights give the same features for the two layouts of the same pixels."""

import torch

from zenrl.common.networks import ConvEncoder


def test_stack_first_equals_channels_last():
    torch.manual_seed(0)
    chw, hwc = ConvEncoder((4, 84, 84)), ConvEncoder((84, 84, 4))
    assert chw.channels_first and not hwc.channels_first
    hwc.load_state_dict(chw.state_dict())
    x = torch.randint(0, 256, (3, 4, 84, 84), dtype=torch.uint8)
    torch.testing.assert_close(chw(x), hwc(x.permute(0, 2, 3, 1).contiguous()))
    assert chw.out_dim == 3136  # the Nature DQN torso: 64 x 7 x 7


def test_camera_image_stays_channels_last():
    assert not ConvEncoder((64, 64, 3)).channels_first
