"""Entry points of the console scripts formation-sim, -headless, -check, -generate and -campaign."""
