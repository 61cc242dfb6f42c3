"""`CallerReports.surface`: the writer errors, raised with the non-finite values that
would have raised noted on them."""

import pytest

from jaxmetrics._host._errors import CallerReports, WriterError


def test_writer_error_notes_the_nonfinite_values_that_would_have_raised():
    reports = CallerReports(packer=None, nonfinite=lambda found: [], nonfinite_tags=())
    reports._nonfinite_messages = lambda report: [("step 3, run 0: term 'r'", "raise")]
    reports.check_later(3, (0,), None)
    reports.error(OSError("disk full"))
    with pytest.raises(WriterError, match="disk full") as caught:
        reports.surface()
    assert caught.value.__notes__ == ["Also non-finite values: step 3, run 0: term 'r'"]
