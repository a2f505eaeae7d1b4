"""evcap.acquire: the DAVIS346 driver, the replay backend and the recorder."""
