"""Tire models behind one interface (`TireModel.forces`), and their compiled kernels."""

from roadgrip.validation import check_choice
from roadgrip.vehicle.tires.base import TireModel
from roadgrip.vehicle.tires.burckhardt import BurckhardtTire
from roadgrip.vehicle.tires.dugoff import DugoffTire
from roadgrip.vehicle.tires.magic_formula import MagicFormulaTire

TIRE_MODELS = {cls.name: cls for cls in (DugoffTire, MagicFormulaTire, BurckhardtTire)}


def tire_model_by_name(name: str, **params) -> TireModel:
    check_choice("tire model", "name", name, set(TIRE_MODELS))
    return TIRE_MODELS[name](**params)


__all__ = ["TIRE_MODELS", "BurckhardtTire", "DugoffTire", "MagicFormulaTire", "TireModel", "tire_model_by_name"]
