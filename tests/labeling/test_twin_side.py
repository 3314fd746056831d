"""A marker outside every trained body is not placed where its named twin on the other side
fits better (``boot_match._twin_fits_better``).

The kneeling performer of the 62-marker take, booted from a model of the take's first 900
frames from frame 906 on (an operator's run through the service, then ``evaluate``): both
forearm plates lie outside every trained body (no mirror segment pairs them). The left arm
was not placed yet when the completion put a left forearm marker on the right forearm's point
beside the placed right upper arm, and the left plate was then read onto the right forearm
for the whole take (2,873 wrong labels, the performer booted and the stream online).
"""

from __future__ import annotations

import pytest

from tests.labeling.kneel import kneel_labeled


@pytest.mark.realdata
def test_a_left_forearm_is_not_read_onto_the_right_one(real_path):
    crossed = labeled = 0
    for given, true in kneel_labeled(real_path, 906, 300):
        labeled += 1
        a, b = given[0], true[0]  # (the side letters)
        crossed += a in "LR" and b in "LR" and a != b
    assert labeled > 13_000  # (booted: 12,617 before, the right forearm unlabeled)
    assert crossed == 0  # (717 before)
