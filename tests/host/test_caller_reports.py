"""`CallerReports.surface`: the writer errors, raised with the non-finite values that
would have raised noted on them (on every supported Python: `add_note` is 3.11's)."""

import pytest

from jaxmetrics._host._errors import CallerReports, WriterError


def test_writer_error_notes_the_nonfinite_values_that_would_have_raised():
    reports = CallerReports(packer=None, nonfinite=lambda found: [], nonfinite_tags=())
    reports._nonfinite_messages = lambda report: [("step 3, run 0: term 'r'", "raise")]
    reports.check_later(3, (0,), None)
    reports.error(OSError("disk full"))
    with pytest.raises(WriterError, match="disk full") as caught:
        reports.surface()
    text = "\n".join([str(caught.value), *getattr(caught.value, "__notes__", [])])
    assert "Also non-finite values: step 3, run 0: term 'r'" in text
