"""One run() per stage. All disk I/O of the pipeline lives here."""
