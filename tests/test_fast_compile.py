"""make test's fast-compile XLA flags (tests/fast_compile.py, issue 64): only those the installed jaxlib knows are
used (XLA aborts on one it does not), and the user's own flags are what is left when they are taken out."""

import fast_compile


def test_the_users_flags_are_the_given_ones_less_the_fast_compile_ones():
    given = ("--xla_backend_optimization_level=0 --xla_cpu_max_isa=AVX2 --xla_cpu_use_fusion_emitters=false "
             "--xla_backend_optimization_level=2")
    assert fast_compile.users_xla_flags(given) == "--xla_cpu_max_isa=AVX2"
    assert fast_compile.users_xla_flags("") == ""


def test_a_flag_the_jaxlib_does_not_know_is_left_out(monkeypatch):
    monkeypatch.setattr(fast_compile, "FLAGS", ("--xla_backend_optimization_level=0", "--xla_softac_no_such_flag=1"))
    assert fast_compile.known_flags() == ["--xla_backend_optimization_level=0"]
