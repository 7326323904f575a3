"""The ``train`` command: a learned method for one mode or the mode-conditioned network."""
from __future__ import annotations

import argparse
from pathlib import Path

from exit_decision.cli.arguments import COUNT, SEED, checkpoint, config_options, known, number, policy, renamed
from exit_decision.config import load_project
from exit_decision.errors import UsageError
from exit_decision.model.names import algorithm_name, run_name


def cmd_train(args: argparse.Namespace) -> int:
    """Train a learned method (one mode or the conditioned network); writes policy.pt, logs and config."""
    from exit_decision.learning.trainer import Trainer
    from exit_decision.model.names import CONDITIONED

    config = load_project(args.config_dir, args.scenario_override, args.override)
    known('--algorithm', args.algorithm, config.training.method)
    if args.conditioning != CONDITIONED:
        known('--conditioning', args.conditioning, config.mode)
    episodes = args.episodes or config.training.episodes
    steps = config.training.of_method(args.algorithm).environment_steps
    if args.episodes and steps:
        raise UsageError(f'--episodes {args.episodes}: this config\'s budget for {args.algorithm} is environment_steps: '
                         f'{steps}; give one budget (drop --episodes, or set environment_steps to null with --override)')
    if args.address:
        if not args.actors:
            raise UsageError(f'--address {args.address}: only with --actors N (N >= 1)')
        from exit_decision.learning.actors import check_address
        check_address(args.address)   # now, not after the demonstrations
    run = run_name(algorithm_name(args.algorithm, args.action_space, False), args.conditioning)   # grid and options apart
    out_dir = args.out or Path('runs') / f'{run}_seed{args.seed}'
    if args.reward_variant:
        known('--reward-variant', args.reward_variant, config.reward)
        config = config.model_copy(update={'env': config.env.model_copy(update={'reward_variant': args.reward_variant})})
    trainer = Trainer(config, args.algorithm, args.conditioning, args.seed, out_dir, args.action_space)
    policy = trainer.run(episodes, resume=args.resume, init=args.init, actors=args.actors, address=args.address)
    if args.actors:
        counts = trainer.actor_counts
        print(f'{args.actors} actors: {counts.restarts} episode(s) given again after an actor died, '
              f'{len(counts.dropped)} actor(s) dropped past actors.max_restarts')
    print(f'best policy: {policy} (validation score {trainer.state.best_score:.3f}); logs in {out_dir}')
    return 0


def cmd_anchor(args: argparse.Namespace) -> int:
    """An anchored policy from training runs, its (kappa, margin) chosen on the validation seeds."""
    from exit_decision.learning.anchoring import tune_anchor

    config = load_project(args.config_dir, args.scenario_override, args.override)
    if args.reward_variant:
        known('--reward-variant', args.reward_variant, config.reward)
        config = config.model_copy(update={'env': config.env.model_copy(update={'reward_variant': args.reward_variant})})
    chosen, score, per_mode = tune_anchor(config, args.policy, args.kappa or [0.0, 1.0, 2.0], args.margin or [0.0],
                                          args.episodes, args.out, args.jobs, args.invocation)
    print(f'anchored policy: {args.out / "policy.pt"}, kappa {chosen.kappa:g}, margin {chosen.margin:g} (validation '
          f'score {score:.3f}); every point in {args.out / "anchor.csv"}')
    for mode, row in per_mode.items():
        print(f'  {mode}: return - the best fixed driver {row["gain"]:+.3f} [{row["gain_low"]:+.3f}, '
              f'{row["gain_high"]:+.3f}], departures from the prior {row["departures"]:.1%}')
    return 0


#: train --help's examples
TRAIN_EXAMPLES = '''examples:
  # the shipped policy, the MDGQN over options for every mode (as scripts/train_policies trains it)
  exit-decision train --algorithm mdgqn --conditioning conditioned --action-space options --override config/overrides/options_no_demonstrations.yaml --seed 2 --episodes 800 --out runs/mdgqn_options_conditioned
  # a per-mode GQN on the 81-action grid (none ships), then the stack on it: its directory is <method>_<mode>
  exit-decision train --algorithm gqn --conditioning CONP --seed 1 --out runs/per_mode/gqn_CONP
  exit-decision stack --policy runs/per_mode/gqn_CONP --start-mode CONP --switch-to ""
  # a short trial of the default (the conditioned MDGQN on the grid: demonstrations, pre-training, RL)
  exit-decision train --episodes 20 --out runs/trial
'''


def add_commands(commands: argparse._SubParsersAction) -> None:
    """Adds ``train``."""
    train = commands.add_parser('train', help='train a learned method (GQN, MDGQN, the baselines) for a mode or all',
                                epilog=TRAIN_EXAMPLES)
    config_options(train)
    train.add_argument('--algorithm', default='mdgqn',
                       help='a method of config/training.yaml: gqn, mdgqn, dqn, ddqn, dueling_dqn, dueling_ddqn_per, '
                            'dueling_ddqn, sgrl, mgrl, ngrl, and each baseline as published (<name>_published, e.g. dqn_published)')
    renamed(train, '--mode', train.add_argument(
        '--conditioning', default='conditioned',
        help='conditioned (one network for every mode, trained on all by relabelling) or a mode of '
             'config/modes.yaml (a network for that mode alone)'))
    train.add_argument('--episodes', type=COUNT, default=None,
                       help="RL episodes (default: config/training.yaml's episodes; refused when the config's budget "
                            "is environment_steps)")
    train.add_argument('--seed', type=SEED, default=0, help='training seed (episodes on seeds seed x 1000000 + episode)')
    train.add_argument('--out', type=Path, default=None,
                       help='run directory, refused if it holds an earlier run unless --resume (default: '
                            'runs/<algorithm>[_options]_<mode>_seed<seed>)')
    train.add_argument('--resume', type=checkpoint, default=None,
                       help='a last.pt to continue from (default: a new run)')
    train.add_argument('--init', type=policy, default=None,
                       help='a policy whose network starts the RL phase (no pre-training): a directory name under '
                            'policies/ or the path of a policy directory or of a checkpoint (default: a new network)')
    train.add_argument('--reward-variant', default=None, help='a variant of config/reward.yaml (default: env.yaml)')
    train.add_argument('--action-space', choices=['grid', 'options'], default='grid',
                       help='the 81-action grid (paper 000) or options (config/env.yaml options: a lane intent x a '
                            'driving style, held until it ends, executed by the rule-based low level)')
    train.add_argument('--actors', type=COUNT, default=0,
                       help='collect the RL episodes on this many Ray actors, one simulation each, and learn here '
                            '(config/training.yaml actors; 0: collect in this process)')
    train.add_argument('--address', default=None,
                       help='with --actors: a running Ray cluster, host:port of its head (default: a local Ray on '
                            'loopback)')
    train.set_defaults(func=cmd_train)

    anchor = commands.add_parser(
        'anchor', help='one policy of several training runs over options, departing from their prior only where '
                       'their lower confidence bound beats a margin (docs/design.md, "Learning")',
        epilog='example:\n  exit-decision anchor --policy runs/seed_1/policy.pt --policy runs/seed_2/policy.pt '
               '--policy runs/seed_3/policy.pt --kappa 0 --kappa 1 --margin 0 --margin 0.05 --out runs/anchored')
    config_options(anchor)
    anchor.add_argument('--policy', type=policy, action='append', required=True,
                        help='a member, a conditioned run over options: its name under policies/, its directory or its policy.pt (repeat: one per training seed)')
    anchor.add_argument('--kappa', type=number(float, 0.0), action='append', default=None,
                        help='a width of the lower bound, in the members\' standard deviations (repeat; default: 0 1 2)')
    anchor.add_argument('--margin', type=number(float, 0.0), action='append', default=None,
                        help='what the bound must beat to depart from the prior, in the learning reward\'s units '
                             '(repeat; default: 0)')
    anchor.add_argument('--episodes', type=COUNT, default=50, help='validation seeds per mode (from 900000)')
    anchor.add_argument('--jobs', type=COUNT, default=1, help='validations run at once, one process each')
    anchor.add_argument('--reward-variant', default=None,
                        help='a variant of config/reward.yaml the returns are scored under (default: env.yaml)')
    anchor.add_argument('--out', type=Path, required=True,
                        help='where the candidates, anchor.csv, anchor.json and the chosen policy.pt go')
    anchor.set_defaults(func=cmd_anchor)
