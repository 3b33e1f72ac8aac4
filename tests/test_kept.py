import torch

from securegs_warp.kept import Kept


def test_kept_value_is_derived_again_only_when_a_source_changes():
    kept, calls = Kept(), []

    def derive():
        calls.append(1)
        return len(calls)

    a, b, label = torch.zeros(3), torch.ones(2), object()
    assert kept.get((a, b, label), derive) == 1
    assert kept.get((a, b, label), derive) == 1  # same objects, no in-place write: kept
    a.add_(1.0)  # an in-place write bumps the tensor's version
    assert kept.get((a, b, label), derive) == 2
    assert kept.get((a.clone(), b, label), derive) == 3  # equal values, another tensor
    assert kept.get((a, b, object()), derive) == 4  # another non-tensor source
    assert kept.get((a, b), derive) == 5  # fewer sources
    assert kept.get((a, b), derive) == 5
