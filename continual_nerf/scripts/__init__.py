"""Command-line tools installed with the plugin."""
