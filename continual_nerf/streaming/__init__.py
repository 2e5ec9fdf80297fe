"""Training on a capture folder that is still being written: its datamanager and the replay-capture command."""
