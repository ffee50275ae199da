from __future__ import annotations

import pytest


def test_fewer_than_two_starts_are_refused_naming_the_option(tmp_path, capsys):
    import bench_worker_start

    with pytest.raises(SystemExit) as info:
        bench_worker_start.main(["--repeats", "1", "--output", str(tmp_path / "out.json")])
    assert info.value.code == 2 and "--repeats must be >= 2" in capsys.readouterr().err
    assert not (tmp_path / "out.json").exists()
