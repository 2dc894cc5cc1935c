"""STREP Studio's web service (FastAPI, job store, executors, viewers). Built on `strep_core`."""
