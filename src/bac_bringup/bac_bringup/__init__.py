"""Graph launcher and command-line entry points of bac: profiles (sim, car, replay), process
supervision and network isolation.
"""
