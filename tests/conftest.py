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


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory, device):
    """Two 8-frame drives of the `tiny` suite (room, corridor), simulated once per session."""
    import dataclasses

    from acoustic_sim.datasets.generate import generate
    from acoustic_sim.datasets.suites import SUITES, Physics

    suite = dataclasses.replace(SUITES["tiny"], variants={"": Physics(ray_count=2000)})
    out = tmp_path_factory.mktemp("tiny_dataset")
    generate(suite, out, frames=16, shards=2, seed=3, device=device, progress=False)
    return out


@pytest.fixture(scope="session")
def three_elevations(tmp_path_factory, device):
    """The tiny_dataset's drives (same suite, seed and rays) beamformed at -20, 0 and 20 deg."""
    import dataclasses

    from acoustic_sim.datasets.generate import generate
    from acoustic_sim.datasets.suites import SUITES, Physics

    suite = dataclasses.replace(SUITES["tiny"], variants={"": Physics(ray_count=2000)})
    suite = dataclasses.replace(suite, settings=("processing.elevation_deg=[-20, 0, 20]",))
    out = tmp_path_factory.mktemp("three_elevations")
    generate(suite, out, frames=16, shards=2, seed=3, device=device, progress=False)
    return out
