"""The QoS profiles of the metampc graph, each defined once so that both ends of a topic agree.

Every profile of metampc's own topics is reliable: the lockstep plant waits for the answer to
each sample, and a lost sample or model would make a seeded run irreproducible. A machine's
own topics, read by the bridge, are best effort (:data:`MACHINE`). docs/plant.md,
controller.md, learner.md and bridge.md list the profile of every topic.
"""
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

# The readers in the loop (the plant's u, the controller's y) and /clock: volatile; the loop
# waits for them, so they are never far behind.
STREAM = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)
# The plant's y, the controller's u and mpc_status, for readers outside the loop that must see
# every message (the learner's D_target, the recorder, the soak observer): a lockstep loop runs
# at 300-1400 Hz and does not wait for them, so a reader whose process gets no CPU falls
# behind, and keep_last drops its oldest unread samples. 1000 deep: about a second behind
# before one is lost (with STREAM's 100, the learner of a CI experiment on a loaded 2-core
# machine lost 12 of its 120 samples, and a recorder 63 of a tracking run's 300 answers when
# two seeds ran at once). Publisher and reader both keep that many.
BACKLOG = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
# Latched state (plant_info, nssm_weights): only the newest message counts, and a node that
# starts later still gets it.
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
# Occasional messages of which a reader needs the newest (reference set-points, training
# progress): rclpy's default profile, keep_last 10.
SPARSE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
# The orchestrator's experiment events: transient_local and deep, so a recorder that matches
# late still gets the events published before (the analysis reads the phases from them).
EVENTS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.TRANSIENT_LOCAL)
# A machine's own topics, read by the bridge: best effort matches any writer, reliable or best
# effort (a sensor driver's is often best effort, and a reliable reader would get nothing).
MACHINE = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT,
                     durability=DurabilityPolicy.VOLATILE)
