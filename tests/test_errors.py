from warpsense.errors import first_line


def test_first_line_of_a_long_message_or_the_type_of_an_empty_one():
    assert first_line(RuntimeError("\n  CUDA error: operation not permitted\nstack trace ...")) == \
        "CUDA error: operation not permitted"
    assert first_line(ValueError("")) == "ValueError"
    assert first_line(KeyError()) == "KeyError"
