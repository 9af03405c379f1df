import sys

try:
    from harness.cli import entry
except KeyboardInterrupt:  # Ctrl-C while still importing: nothing was written yet
    print("harness: interrupted", file=sys.stderr)
    sys.exit(130)

entry()
