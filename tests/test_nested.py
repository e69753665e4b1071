"""The nested-table comparison used by the end-to-end tests rejects what it should."""

import numpy as np
import pytest

from tests.nested import assert_nested_close

TABLE = {"fbp": {"psnr": [15.39, 0.0144], "ssim": [0.5, 0.01]}, "ours": {"psnr": [20.0, 0.5]}}


def test_equal_tables_pass_json_turns_tuples_into_lists():
  same = {"fbp": {"psnr": (15.39, np.float32(0.0144)), "ssim": [0.5, 0.01]},
          "ours": {"psnr": np.array([20.0, 0.5])}}
  assert_nested_close(same, TABLE, rtol=1e-6)


@pytest.mark.parametrize("change, message", [
    (lambda t: t["fbp"]["psnr"].__setitem__(0, 15.40), "/fbp/psnr"),   # a value, 6.5e-4 relative
    (lambda t: t["ours"].pop("psnr"), "keys differ"),                  # a metric missing
    (lambda t: t.__setitem__("lct", {}), "keys differ"),               # a method too many
    (lambda t: t["fbp"]["ssim"].append(0.0), "length"),                # a longer row
    (lambda t: t["ours"].__setitem__("psnr", 20.0), "sequence"),       # a scalar for a row
])
def test_any_difference_fails_and_names_where(change, message):
  other = {m: {k: list(v) for k, v in row.items()} for m, row in TABLE.items()}
  change(other)
  with pytest.raises(AssertionError, match=message):
    assert_nested_close(other, TABLE, rtol=1e-5)
