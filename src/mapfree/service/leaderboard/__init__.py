"""The evaluation server: submissions stored and queued, workers scoring them, what a result may show, the boards."""
