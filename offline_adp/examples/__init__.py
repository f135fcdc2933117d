"""Documented examples from the chapter, runnable and tested."""
