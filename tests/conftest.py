import pytest
import warp as wp

wp.config.quiet = True
wp.config.log_level = wp.LOG_WARNING


def pytest_addoption(parser):
    parser.addoption("--device", default="cpu", help="Warp device for simulation tests (cpu, cuda:0, ...)")


@pytest.fixture(scope="session")
def device(request):
    name = request.config.getoption("--device")
    wp.init()
    if not wp.is_device_available(wp.get_device(name)):
        pytest.fail(f"Warp device {name!r} is not available here")
    return name
