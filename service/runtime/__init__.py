"""The one runner loop and what it plugs together: sources, sinks, clocks, health,
persistence, and the replay harness built on them."""
