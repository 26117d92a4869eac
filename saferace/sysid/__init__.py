"""System identification of the MuJoCo car: manoeuvres, fits and prediction errors."""
