import numpy as np
import pytest
import torch
from PIL import Image

from anycity.export.views import save_view_pngs, view_png


def test_views_are_saved_under_their_index_and_read_back_to_within_rounding(tmp_path):
    images = torch.rand(2, 3, 8, 12)
    save_view_pngs(tmp_path, "inputs", images, [5, 17])
    assert sorted(p.name for p in (tmp_path / "inputs").iterdir()) == ["005.png", "017.png"]
    back = np.asarray(Image.open(view_png(tmp_path, "inputs", 17)))
    assert back.shape == (8, 12, 3)
    assert np.abs(back / 255.0 - images[1].permute(1, 2, 0).numpy()).max() <= 0.5 / 255 + 1e-6


def test_a_view_index_per_image():
    with pytest.raises(ValueError, match="2 images for 1 view indices"):
        save_view_pngs("unused", "renders", torch.zeros(2, 3, 4, 4), [0])
