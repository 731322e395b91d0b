"""Consists as data: the scenario's ``train`` section (:mod:`canbrake.consist.components`).

A vehicle type is a composition of components (resistance, coupler, brake, traction, wheels), each
kind a registry of named models with a pydantic parameter schema. The assembler lowers a train onto
the physics kernel its components call for; the kernel configurations (:mod:`~canbrake.consist.coupled`,
:mod:`~canbrake.consist.heavy_haul`, :mod:`~canbrake.consist.adhesion`) are internal.
"""
