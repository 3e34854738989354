"""Finite elements: materials, shell and solid elements (linear and corotational), the models
(the Model protocol, ShellModel, SolidModel), factorizations and full-order nonlinear statics."""
