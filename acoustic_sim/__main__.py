import sys

try:
    from .cli import main
except KeyboardInterrupt:  # Ctrl-C while the command line loads: nothing was started or written
    print("interrupted", file=sys.stderr)
    sys.exit(130)

sys.exit(main())
