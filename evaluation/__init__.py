"""Measurement code shared by the tests and the benchmarks: real pairs with ground truth, reference implementations,
accuracy runs. Sits above the core and the plants (`sim`); nothing of the service imports it."""
