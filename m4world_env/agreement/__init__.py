"""Agreement between the world-model backend and the ground truth over a zoo of policies.

:mod:`~m4world_env.agreement.run` runs the zoo on both backends (``m4world agreement``),
:mod:`~m4world_env.agreement.stats` compares the scores, :mod:`~m4world_env.agreement.render` writes
the report and :mod:`~m4world_env.agreement.video` the side-by-side videos. The run sizes live here,
where the command line reads them without loading a model.
"""

# The default run's size is set by the world model's cost on a 2-core CPU without native bf16 (its
# report gives its time): three scenarios of different roads and light, two seeds, 4 s of driving
# (a policy step is 0.2 s in every bundled scenario).
DEFAULT_SCENARIOS = ("highway_sunny_day", "merge_cut_in", "two_way_overtake_dusk")
DEFAULT_SEEDS = 2
DEFAULT_STEPS = 20
# --full: six scenarios (highway in sun and rain, a merge, a two-way road, fog on a roundabout, snow
# with a stopped vehicle), four seeds, the same 4 s episodes.
FULL_SCENARIOS = (
    "highway_sunny_day",
    "highway_dense_rain_dusk",
    "merge_cut_in",
    "two_way_overtake_dusk",
    "roundabout_fog",
    "stopped_vehicle_snow",
)
FULL_SEEDS = 4
FULL_STEPS = DEFAULT_STEPS
DEFAULT_VIDEOS = 3
