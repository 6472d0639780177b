"""M4World-Gym: Gymnasium environments whose dynamics are the M4World world model."""
