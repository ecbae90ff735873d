"""tissue.compilation counts each kernel instance once, on its first launch, and times that compile."""

import math

import pytest
import taichi as ti

from tissue import compilation


def test_first_launch_of_each_instance_is_counted_and_timed(backend):
    values = ti.field(ti.f64, 8)

    @ti.kernel
    def fill(a: ti.f64):
        for i in values:
            values[i] = ti.sin(a * i)

    @ti.kernel
    def shift(offset: ti.template()):
        for i in values:
            values[i] += offset

    start = compilation.snapshot()
    fill(1.0)
    first = compilation.snapshot() - start
    assert first.count == 1 and first.seconds > 0
    assert compilation.seconds_by_kernel()["fill"] == pytest.approx(first.ir_seconds)   # its only instance
    assert 0 < compilation.seconds_by_kernel(cpu=True)["fill"]
    fill(2.0)
    assert compilation.snapshot() - start == first          # same instance: nothing compiled
    shift(1)
    shift(2)                                                # another template value: another instance
    shift(2)
    assert (compilation.snapshot() - start).count == 3
    mine = compilation.instances()[-3:]                     # one record per instance, in order, all three parts
    assert [i.kernel for i in mine] == ["fill", "shift", "shift"]
    assert all(i.frontend_s > 0 and i.module_s > 0 and i.machine_code_s > 0 for i in mine)
    assert compilation.count() >= 3 and compilation.seconds() >= first.seconds
    assert values[3] == pytest.approx(math.sin(2.0 * 3) + 5)


def test_install_is_idempotent(backend):
    compilation.install()
    compilation.install()

    @ti.kernel
    def one() -> ti.i32:
        return 1

    start = compilation.count()
    assert one() == 1
    assert compilation.count() - start == 1


def test_the_first_launch_is_timed_as_machine_code_once_per_instance(backend):
    @ti.kernel
    def twice(a: ti.f64) -> ti.f64:
        return 2 * a

    start = compilation.snapshot()
    assert twice(1.0) == 2.0
    first = compilation.snapshot() - start
    assert first.count == 1 and first.ir_seconds > 0 and first.machine_code_seconds > 0
    assert first.seconds == pytest.approx(first.ir_seconds + first.machine_code_seconds)
    assert twice(2.0) == 4.0
    assert compilation.snapshot() - start == first          # a later launch is not compilation
