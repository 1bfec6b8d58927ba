"""The lab: what measures, trains and replays the flight service, never imported by it.

``evaluation`` flies the service's cores against the simulator (scenarios, Monte Carlo, Ray campaigns,
auto-label checks); ``training`` trains, fine-tunes, evaluates and exports the leader detector; ``bench``
times perception; ``replay`` runs perception on recordings. The lab may import the service and the
simulator; the import rules in ``pyproject.toml`` keep the service from importing the lab.
"""
