"""The ``trace3d bench <name>`` harnesses, kept out of the runtime packages: nothing in a pipeline step
imports this package, so a change to a benchmark reruns no step.

    render.py     ``bench render``: the tile kernels against the dense reference, forward + backward, trace
    synthetic.py  ``bench synthetic``: the synthetic room generator's ray caster
    fit.py        ``bench fit`` (phases of a training iteration, rounds, a baseline checkout side by side) and
                  ``bench fit-sweep`` (Gaussian budget x iterations against test PSNR)
    trace.py      ``bench trace``: GIT, merge and refinement on a fitted room
    merge_vote.py ``bench merge-vote``: what the merges' votes separate, pair by pair, against the truth
    lift.py       ``bench lift`` (one contrastive iteration, sparse path vs rasterizer) and ``bench lift-forms``
    prompts.py    ``bench prompts``: how well each prompt source answers self-prompting's point prompts
    evaluate.py   ``bench evaluate``: the evaluate step of one (scene, variant, protocol), seconds per phase
    startup.py    ``bench startup``: every pipeline step's cost before its first line (fresh processes)

Each returns one JSON-serialisable dict, which ``trace3d bench`` prints (and writes with ``--out``).
"""
