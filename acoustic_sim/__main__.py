import signal
import sys

# A Ctrl-C while the command line loads is held until it has loaded, then stops it: Python's import
# machinery runs weakref callbacks whose exceptions it only prints ("Exception ignored in ...
# _get_module_lock"), so a KeyboardInterrupt landing in one was lost and the command ran on (CI,
# tests/test_probe_sim.py at 0.05 s). A SIGINT that is ignored (started in the background) stays so.
held: list[bool] = []
holding = signal.getsignal(signal.SIGINT) is signal.default_int_handler
if holding:
    signal.signal(signal.SIGINT, lambda *_: held.append(True))
try:
    from .cli import main
except KeyboardInterrupt:  # raised by a library's own handling: nothing was started or written
    held.append(True)
finally:
    if holding:
        signal.signal(signal.SIGINT, signal.default_int_handler)
if held:
    print("interrupted", file=sys.stderr)
    sys.exit(130)

sys.exit(main())
