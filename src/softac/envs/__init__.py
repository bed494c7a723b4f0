"""Environments: make and check them, wrappers, images, goal layout, exact env state, worker pools, families."""
