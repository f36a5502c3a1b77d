"""The `zoo` command: parses arguments, calls the pipeline or the runtime, prints."""
