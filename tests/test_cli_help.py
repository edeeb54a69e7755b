"""``--help`` that leads (issue 33): each command's usage line and first screen show the flags most runs
need, the others sit in named groups in one order, and grouping them changed no flag: every flag parses
to the same dest, type and default as before (the contract below, captured from the parser before the
flags were grouped)."""

from __future__ import annotations

import argparse
import re
from typing import Any

import pytest

from memlog.cli.app import build_parser, main
from memlog.cli.flags import GROUPS

#: Every action of every subcommand as the parser built it before its flags were grouped (captured from
#: that parser by a script): (command, option strings, dest, default, type, action, nargs, const,
#: choices, required). Grouping changes where --help shows a flag, never this. Flags added since are
#: added here with their command.
CONTRACT = {
    ('batch', ('--actors-per-gpu',), 'actors_per_gpu', None, 'positive_int', '_StoreAction', None, None, None, False),
    ('batch', ('--all-scores',), 'all_scores', None, None, '_StoreTrueAction', 0, True, None, False),
    ('batch', ('--candidates',), 'candidates', None, 'count_or_all', '_StoreAction', None, None, None, False),
    ('batch', ('--config',), 'config', None, None, '_StoreAction', None, None, None, False),
    ('batch', ('--dedup',), 'dedup', None, 'cosine_distance', '_StoreAction', None, None, None, False),
    ('batch', ('--descriptor',), 'descriptor', None, None, '_StoreAction', None, None, None, False),
    ('batch', ('--descriptor-dtype',), 'descriptor_dtype', None, None,
     '_StoreAction', None, None, ('float32', 'float16'), False),
    ('batch', ('--device',), 'device', None, None, '_StoreAction', None, None, ('auto', 'cpu', 'cuda'), False),
    ('batch', ('--distinct-weight',), 'distinct_weight', None, 'nonneg_float',
     '_StoreAction', None, None, None, False),
    ('batch', ('--dt',), 'dt', None, 'unit_interval', '_StoreAction', None, None, None, False),
    ('batch', ('--duplicates',), 'duplicates', None, None,
     '_StoreAction', None, None, ('identical', 'near', 'off'), False),
    ('batch', ('--et',), 'et', None, 'unit_interval', '_StoreAction', None, None, None, False),
    ('batch', ('--fast',), 'mode', None, None, '_StoreConstAction', 0, 'fast', None, False),
    ('batch', ('--image-format',), 'image_format', None, None, '_StoreAction', None, None, ('jpeg', 'png'), False),
    ('batch', ('--jpeg-quality',), 'jpeg_quality', None, 'int_range.<locals>.check',
     '_StoreAction', None, None, None, False),
    ('batch', ('--keep-fraction',), 'keep_fraction', None, 'fraction', '_StoreAction', None, None, None, False),
    ('batch', ('--keep-topic',), 'keep_topic', None, None, '_AppendAction', None, None, None, False),
    ('batch', ('--logs-at-once',), 'logs_at_once', None, 'positive_int', '_StoreAction', None, None, None, False),
    ('batch', ('--manifest',), 'manifest', None, None, '_StoreAction', None, None, None, False),
    ('batch', ('--max-pixels',), 'max_pixels', None, 'positive_int', '_MaxPixels', None, None, None, False),
    ('batch', ('--max-retries',), 'max_retries', None, 'nonneg_int', '_StoreAction', None, None, None, False),
    ('batch', ('--mt',), 'mt', None, 'unit_interval', '_StoreAction', None, None, None, False),
    ('batch', ('--near-distance',), 'near_distance', None, 'open_unit_interval',
     '_StoreAction', None, None, None, False),
    ('batch', ('--no-refine',), 'fast_refine', None, None, '_StoreFalseAction', 0, False, None, False),
    ('batch', ('--no-resume',), 'no_resume', False, None, '_StoreTrueAction', 0, True, None, False),
    ('batch', ('--no-whiten',), 'no_whiten', False, None, '_StoreTrueAction', 0, True, None, False),
    ('batch', ('--normalize',), 'normalize', None, None, '_StoreAction', None, None, ('all', 'static'), False),
    ('batch', ('--paper-literal',), 'mode', None, None, '_StoreConstAction', 0, 'paper', None, False),
    ('batch', ('--position-topic',), 'position_topic', None, None, '_StoreAction', None, None, None, False),
    ('batch', ('--preset',), 'preset', None, None, '_StoreAction', None, None, ('paper', 'st-lucia'), False),
    ('batch', ('--ray',), 'ray', None, 'ray_address', '_StoreAction', '?', 'local', None, False),
    ('batch', ('--score-kept',), 'score_kept', None, None, '_StoreTrueAction', 0, True, None, False),
    ('batch', ('--segment-by',), 'segment_by', None, None,
     '_StoreAction', None, None, ('auto', 'distance', 'time', 'count', 'view'), False),
    ('batch', ('--select',), 'select', None, None, '_StoreAction', None, None, ('paper', 'segment'), False),
    ('batch', ('--spacing-m',), 'spacing_m', None, 'positive_float', '_StoreAction', None, None, None, False),
    ('batch', ('--spacing-s',), 'spacing_s', None, 'positive_float', '_StoreAction', None, None, None, False),
    ('batch', ('--spacing-view',), 'spacing_view', None, 'positive_float', '_StoreAction', None, None, None, False),
    ('batch', ('--st',), 'st', None, 'unit_interval', '_StoreAction', None, None, None, False),
    ('batch', ('--stride',), 'stride', None, 'positive_int', '_StoreAction', None, None, None, False),
    ('batch', ('--summary',), 'summary', None, None, '_StoreAction', None, None, None, False),
    ('batch', ('--threads',), 'threads', None, 'nonneg_int', '_StoreAction', None, None, None, False),
    ('batch', ('--whiten-dim',), 'whiten_dim', None, 'positive_int', '_StoreAction', None, None, None, False),
    ('batch', ('--workers',), 'workers', None, 'positive_int', '_StoreAction', None, None, None, False),
    ('batch', ('-o', '--output'), 'output', None, None, '_StoreAction', None, None, None, True),
    ('batch', ('-q', '--quiet'), 'quiet', '==SUPPRESS==', None, '_StoreTrueAction', 0, True, None, False),
    ('batch', ('-t', '--topic'), 'topics', None, None, '_AppendAction', None, None, None, False),
    ('batch', (), 'logs', None, None, '_StoreAction', '*', None, None, True),
    ('convert', ('--compression',), 'compression', 'zstd', None,
     '_StoreAction', None, None, ('zstd', 'lz4', 'none'), False),
    ('convert', ('-o', '--output'), 'output', None, None, '_StoreAction', None, None, None, True),
    ('convert', ('-q', '--quiet'), 'quiet', '==SUPPRESS==', None, '_StoreTrueAction', 0, True, None, False),
    ('convert', (), 'log', None, None, '_StoreAction', None, None, None, True),
    ('evaluate', ('--all-scores',), 'all_scores', None, None, '_StoreTrueAction', 0, True, None, False),
    ('evaluate', ('--candidates',), 'candidates', None, 'count_or_all', '_StoreAction', None, None, None, False),
    ('evaluate', ('--causal',), 'causal', False, None, '_StoreTrueAction', 0, True, None, False),
    ('evaluate', ('--compare-exact',), 'compare_exact', False, None, '_StoreTrueAction', 0, True, None, False),
    ('evaluate', ('--config',), 'config', None, None, '_StoreAction', None, None, None, False),
    ('evaluate', ('--coordinate',), 'coordinate', None, None,
     '_StoreAction', None, None, ('auto', 'frames', 'time', 'positions'), False),
    ('evaluate', ('--dedup',), 'dedup', None, 'cosine_distance', '_StoreAction', None, None, None, False),
    ('evaluate', ('--descriptor',), 'descriptor', None, None, '_StoreAction', None, None, None, False),
    ('evaluate', ('--device',), 'device', None, None, '_StoreAction', None, None, ('auto', 'cpu', 'cuda'), False),
    ('evaluate', ('--distinct-weight',), 'distinct_weight', None, 'nonneg_float',
     '_StoreAction', None, None, None, False),
    ('evaluate', ('--dt',), 'dt', None, 'unit_interval', '_StoreAction', None, None, None, False),
    ('evaluate', ('--duplicates',), 'duplicates', None, None,
     '_StoreAction', None, None, ('identical', 'near', 'off'), False),
    ('evaluate', ('--end',), 'end', None, 'log_time', '_StoreAction', None, None, None, False),
    ('evaluate', ('--et',), 'et', None, 'unit_interval', '_StoreAction', None, None, None, False),
    ('evaluate', ('--fast',), 'mode', None, None, '_StoreConstAction', 0, 'fast', None, False),
    ('evaluate', ('--keep-fraction',), 'keep_fraction', None, 'fraction', '_StoreAction', None, None, None, False),
    ('evaluate', ('--keep-stops',), 'keep_stops', False, None, '_StoreTrueAction', 0, True, None, False),
    ('evaluate', ('--max-frames',), 'max_frames', None, 'positive_int', '_StoreAction', None, None, None, False),
    ('evaluate', ('--max-gap',), 'max_gap', None, 'positive_float', '_StoreAction', None, None, None, False),
    ('evaluate', ('--max-pixels',), 'max_pixels', None, 'positive_int', '_MaxPixels', None, None, None, False),
    ('evaluate', ('--mt',), 'mt', None, 'unit_interval', '_StoreAction', None, None, None, False),
    ('evaluate', ('--near-distance',), 'near_distance', None, 'open_unit_interval',
     '_StoreAction', None, None, None, False),
    ('evaluate', ('--no-refine',), 'fast_refine', None, None, '_StoreFalseAction', 0, False, None, False),
    ('evaluate', ('--no-report',), 'no_report', False, None, '_StoreTrueAction', 0, True, None, False),
    ('evaluate', ('--no-rerank',), 'no_rerank', False, None, '_StoreTrueAction', 0, True, None, False),
    ('evaluate', ('--no-hmm',), 'no_hmm', False, None, '_StoreTrueAction', 0, True, None, False),
    ('evaluate', ('--no-ensemble',), 'no_ensemble', False, None, '_StoreTrueAction', 0, True, None, False),
    ('evaluate', ('--no-whiten',), 'no_whiten', False, None, '_StoreTrueAction', 0, True, None, False),
    ('evaluate', ('--normalize',), 'normalize', None, None, '_StoreAction', None, None, ('all', 'static'), False),
    ('evaluate', ('--paper-discarded',), 'paper_discarded', None, None,
     '_StoreAction', None, None, ('false_negative', 'true_negative', 'uncovered_negative'), False),
    ('evaluate', ('--paper-literal',), 'mode', None, None, '_StoreConstAction', 0, 'paper', None, False),
    ('evaluate', ('--preset',), 'preset', None, None, '_StoreAction', None, None, ('paper', 'st-lucia'), False),
    ('evaluate', ('--query',), 'query', None, None, '_StoreAction', None, None, None, True),
    ('evaluate', ('--query-topic',), 'query_topic', None, None, '_StoreAction', None, None, None, False),
    ('evaluate', ('--reference',), 'reference', None, None, '_StoreAction', None, None, None, True),
    ('evaluate', ('--reference-topic',), 'reference_topic', None, None, '_StoreAction', None, None, None, False),
    ('evaluate', ('--seeds',), 'seeds', None, 'positive_int', '_StoreAction', None, None, None, False),
    ('evaluate', ('--segment-by',), 'segment_by', None, None,
     '_StoreAction', None, None, ('auto', 'distance', 'time', 'count', 'view'), False),
    ('evaluate', ('--select',), 'select', None, None, '_StoreAction', None, None, ('paper', 'segment'), False),
    ('evaluate', ('--sequence',), 'sequence', None, 'nonneg_int', '_StoreAction', None, None, None, False),
    ('evaluate', ('--sequence-k',), 'sequence_k', None, 'positive_int', '_StoreAction', None, None, None, False),
    ('evaluate', ('--spacing-m',), 'spacing_m', None, 'positive_float', '_StoreAction', None, None, None, False),
    ('evaluate', ('--spacing-s',), 'spacing_s', None, 'positive_float', '_StoreAction', None, None, None, False),
    ('evaluate', ('--spacing-view',), 'spacing_view', None, 'positive_float', '_StoreAction', None, None, None, False),
    ('evaluate', ('--speed-prior',), 'speed_prior', None, 'nonneg_float', '_StoreAction', None, None, None, False),
    ('evaluate', ('--speeds',), 'speeds', None, 'speed_range', '_StoreAction', None, None, None, False),
    ('evaluate', ('--st',), 'st', None, 'unit_interval', '_StoreAction', None, None, None, False),
    ('evaluate', ('--start',), 'start', None, 'log_time', '_StoreAction', None, None, None, False),
    ('evaluate', ('--stride',), 'stride', 1, 'positive_int', '_StoreAction', None, None, None, False),
    ('evaluate', ('--threads',), 'threads', None, 'nonneg_int', '_StoreAction', None, None, None, False),
    ('evaluate', ('--tolerance',), 'tolerance', None, 'nonneg_float', '_StoreAction', None, None, None, False),
    ('evaluate', ('--truth',), 'truth', None, None, '_StoreAction', None, None, None, False),
    ('evaluate', ('-o', '--output'), 'output', None, None, '_StoreAction', None, None, None, True),
    ('evaluate', ('-q', '--quiet'), 'quiet', '==SUPPRESS==', None, '_StoreTrueAction', 0, True, None, False),
    ('inspect', ('--json',), 'json', False, None, '_StoreTrueAction', 0, True, None, False),
    ('inspect', ('-q', '--quiet'), 'quiet', '==SUPPRESS==', None, '_StoreTrueAction', 0, True, None, False),
    ('inspect', (), 'log', None, None, '_StoreAction', None, None, None, True),
    ('localize', ('--annotate',), 'annotate', None, None, '_StoreAction', None, None, None, False),
    ('localize', ('--causal',), 'causal', False, None, '_StoreTrueAction', 0, True, None, False),
    ('localize', ('--coordinate',), 'coordinate', None, None,
     '_StoreAction', None, None, ('auto', 'frames', 'time', 'positions'), False),
    ('localize', ('--end',), 'end', None, 'log_time', '_StoreAction', None, None, None, False),
    ('localize', ('--json',), 'json', False, None, '_StoreTrueAction', 0, True, None, False),
    ('localize', ('--keep-stops',), 'keep_stops', False, None, '_StoreTrueAction', 0, True, None, False),
    ('localize', ('--map',), 'map_log', None, None, '_StoreAction', None, None, None, False),
    ('localize', ('--max-gap',), 'max_gap', None, 'positive_float', '_StoreAction', None, None, None, False),
    ('localize', ('--max-pixels',), 'max_pixels', None, 'positive_int', '_MaxPixels', None, None, None, False),
    ('localize', ('--nlist',), 'nlist', None, 'positive_int', '_StoreAction', None, None, None, False),
    ('localize', ('--no-rerank',), 'no_rerank', False, None, '_StoreTrueAction', 0, True, None, False),
    ('localize', ('--no-hmm',), 'no_hmm', False, None, '_StoreTrueAction', 0, True, None, False),
    ('localize', ('--no-ensemble',), 'no_ensemble', False, None, '_StoreTrueAction', 0, True, None, False),
    ('localize', ('--nprobe',), 'nprobe', None, 'positive_int', '_StoreAction', None, None, None, False),
    ('localize', ('--query-descriptors',), 'query_descriptors', None, None, '_StoreAction', None, None, None, False),
    ('localize', ('--search',), 'search', 'auto', None, '_StoreAction', None, None, ('auto', 'exact', 'ivf'), False),
    ('localize', ('--sequence',), 'sequence', None, 'nonneg_int', '_StoreAction', None, None, None, False),
    ('localize', ('--sequence-k',), 'sequence_k', None, 'positive_int', '_StoreAction', None, None, None, False),
    ('localize', ('--speed-prior',), 'speed_prior', None, 'nonneg_float', '_StoreAction', None, None, None, False),
    ('localize', ('--speeds',), 'speeds', None, 'speed_range', '_StoreAction', None, None, None, False),
    ('localize', ('--start',), 'start', None, 'log_time', '_StoreAction', None, None, None, False),
    ('localize', ('--stride',), 'stride', 1, 'positive_int', '_StoreAction', None, None, None, False),
    ('localize', ('--time-search',), 'time_search', False, None, '_StoreTrueAction', 0, True, None, False),
    ('localize', ('-k',), 'k', 5, 'positive_int', '_StoreAction', None, None, None, False),
    ('localize', ('-o', '--output'), 'output', None, None, '_StoreAction', None, None, None, True),
    ('localize', ('-q', '--quiet'), 'quiet', '==SUPPRESS==', None, '_StoreTrueAction', 0, True, None, False),
    ('localize', ('-t', '--topic'), 'topics', None, None, '_AppendAction', None, None, None, False),
    ('localize', (), 'map', None, None, '_StoreAction', None, None, None, True),
    ('localize', (), 'query', None, None, '_StoreAction', None, None, None, True),
    ('map', ('--all-scores',), 'all_scores', None, None, '_StoreTrueAction', 0, True, None, False),
    ('map', ('--candidates',), 'candidates', None, 'count_or_all', '_StoreAction', None, None, None, False),
    ('map', ('--config',), 'config', None, None, '_StoreAction', None, None, None, False),
    ('map', ('--dedup',), 'dedup', None, 'cosine_distance', '_StoreAction', None, None, None, False),
    ('map', ('--descriptor',), 'descriptor', None, None, '_StoreAction', None, None, None, False),
    ('map', ('--descriptor-dtype',), 'descriptor_dtype', None, None,
     '_StoreAction', None, None, ('float32', 'float16'), False),
    ('map', ('--descriptors',), 'descriptors', None, None, '_StoreAction', None, None, None, False),
    ('map', ('--device',), 'device', None, None, '_StoreAction', None, None, ('auto', 'cpu', 'cuda'), False),
    ('map', ('--distinct-weight',), 'distinct_weight', None, 'nonneg_float', '_StoreAction', None, None, None, False),
    ('map', ('--dt',), 'dt', None, 'unit_interval', '_StoreAction', None, None, None, False),
    ('map', ('--duplicates',), 'duplicates', None, None,
     '_StoreAction', None, None, ('identical', 'near', 'off'), False),
    ('map', ('--et',), 'et', None, 'unit_interval', '_StoreAction', None, None, None, False),
    ('map', ('--fast',), 'mode', None, None, '_StoreConstAction', 0, 'fast', None, False),
    ('map', ('--image-format',), 'image_format', None, None, '_StoreAction', None, None, ('jpeg', 'png'), False),
    ('map', ('--jpeg-quality',), 'jpeg_quality', None, 'int_range.<locals>.check',
     '_StoreAction', None, None, None, False),
    ('map', ('--json',), 'json', False, None, '_StoreTrueAction', 0, True, None, False),
    ('map', ('--keep-fraction',), 'keep_fraction', None, 'fraction', '_StoreAction', None, None, None, False),
    ('map', ('--keep-topic',), 'keep_topic', None, None, '_AppendAction', None, None, None, False),
    ('map', ('--max-pixels',), 'max_pixels', None, 'positive_int', '_MaxPixels', None, None, None, False),
    ('map', ('--mt',), 'mt', None, 'unit_interval', '_StoreAction', None, None, None, False),
    ('map', ('--near-distance',), 'near_distance', None, 'open_unit_interval',
     '_StoreAction', None, None, None, False),
    ('map', ('--no-refine',), 'fast_refine', None, None, '_StoreFalseAction', 0, False, None, False),
    ('map', ('--no-whiten',), 'no_whiten', False, None, '_StoreTrueAction', 0, True, None, False),
    ('map', ('--normalize',), 'normalize', None, None, '_StoreAction', None, None, ('all', 'static'), False),
    ('map', ('--paper-literal',), 'mode', None, None, '_StoreConstAction', 0, 'paper', None, False),
    ('map', ('--position-topic',), 'position_topic', None, None, '_StoreAction', None, None, None, False),
    ('map', ('--preset',), 'preset', None, None, '_StoreAction', None, None, ('paper', 'st-lucia'), False),
    ('map', ('--score-kept',), 'score_kept', None, None, '_StoreTrueAction', 0, True, None, False),
    ('map', ('--scores',), 'scores', None, None, '_StoreAction', None, None, None, False),
    ('map', ('--segment-by',), 'segment_by', None, None,
     '_StoreAction', None, None, ('auto', 'distance', 'time', 'count', 'view'), False),
    ('map', ('--select',), 'select', None, None, '_StoreAction', None, None, ('paper', 'segment'), False),
    ('map', ('--spacing-m',), 'spacing_m', None, 'positive_float', '_StoreAction', None, None, None, False),
    ('map', ('--spacing-s',), 'spacing_s', None, 'positive_float', '_StoreAction', None, None, None, False),
    ('map', ('--spacing-view',), 'spacing_view', None, 'positive_float', '_StoreAction', None, None, None, False),
    ('map', ('--st',), 'st', None, 'unit_interval', '_StoreAction', None, None, None, False),
    ('map', ('--stride',), 'stride', None, 'positive_int', '_StoreAction', None, None, None, False),
    ('map', ('--threads',), 'threads', None, 'nonneg_int', '_StoreAction', None, None, None, False),
    ('map', ('--whiten-dim',), 'whiten_dim', None, 'positive_int', '_StoreAction', None, None, None, False),
    ('map', ('--workers',), 'workers', None, 'positive_int', '_StoreAction', None, None, None, False),
    ('map', ('-o', '--output'), 'output', None, None, '_StoreAction', None, None, None, True),
    ('map', ('-q', '--quiet'), 'quiet', '==SUPPRESS==', None, '_StoreTrueAction', 0, True, None, False),
    ('map', ('-t', '--topic'), 'topics', None, None, '_AppendAction', None, None, None, False),
    ('map', (), 'log', None, None, '_StoreAction', None, None, None, True),
    ('models', ('--force',), 'force', False, None, '_StoreTrueAction', 0, True, None, False),
    ('models', ('--json',), 'json', False, None, '_StoreTrueAction', 0, True, None, False),
    ('models', ('-q', '--quiet'), 'quiet', '==SUPPRESS==', None, '_StoreTrueAction', 0, True, None, False),
    ('models', (), 'action', 'list', None, '_StoreAction', '?', None, ('list', 'prepare'), False),
    ('models', (), 'names', None, None, '_StoreAction', '*', None, None, True),
    ('score', ('--all-scores',), 'all_scores', None, None, '_StoreTrueAction', 0, True, None, False),
    ('score', ('--config',), 'config', None, None, '_StoreAction', None, None, None, False),
    ('score', ('--device',), 'device', None, None, '_StoreAction', None, None, ('auto', 'cpu', 'cuda'), False),
    ('score', ('--duplicates',), 'duplicates', None, None,
     '_StoreAction', None, None, ('identical', 'near', 'off'), False),
    ('score', ('--end',), 'end', None, 'log_time', '_StoreAction', None, None, None, False),
    ('score', ('--et',), 'et', None, 'unit_interval', '_StoreAction', None, None, None, False),
    ('score', ('--fast',), 'mode', None, None, '_StoreConstAction', 0, 'fast', None, False),
    ('score', ('--maps',), 'maps', False, None, '_StoreTrueAction', 0, True, None, False),
    ('score', ('--max-pixels',), 'max_pixels', None, 'positive_int', '_MaxPixels', None, None, None, False),
    ('score', ('--mt',), 'mt', None, 'unit_interval', '_StoreAction', None, None, None, False),
    ('score', ('--near-distance',), 'near_distance', None, 'open_unit_interval',
     '_StoreAction', None, None, None, False),
    ('score', ('--no-refine',), 'fast_refine', None, None, '_StoreFalseAction', 0, False, None, False),
    ('score', ('--normalize',), 'normalize', None, None, '_StoreAction', None, None, ('all', 'static'), False),
    ('score', ('--paper-literal',), 'mode', None, None, '_StoreConstAction', 0, 'paper', None, False),
    ('score', ('--preset',), 'preset', None, None, '_StoreAction', None, None, ('paper', 'st-lucia'), False),
    ('score', ('--st',), 'st', None, 'unit_interval', '_StoreAction', None, None, None, False),
    ('score', ('--start',), 'start', None, 'log_time', '_StoreAction', None, None, None, False),
    ('score', ('--stride',), 'stride', 1, 'positive_int', '_StoreAction', None, None, None, False),
    ('score', ('--threads',), 'threads', None, 'nonneg_int', '_StoreAction', None, None, None, False),
    ('score', ('--workers',), 'workers', 1, 'positive_int', '_StoreAction', None, None, None, False),
    ('score', ('-o', '--output'), 'output', None, None, '_StoreAction', None, None, None, True),
    ('score', ('-q', '--quiet'), 'quiet', '==SUPPRESS==', None, '_StoreTrueAction', 0, True, None, False),
    ('score', ('-t', '--topic'), 'topics', None, None, '_AppendAction', None, None, None, False),
    ('score', (), 'logs', None, None, '_StoreAction', '+', None, None, True),
}

#: A minimal command line of each subcommand and what it parsed to before, besides the flags' defaults
#: (``func`` by name; batch's parser default ``descriptors``).
MINIMAL = {
    'inspect': (['inspect', 'a.mcap'], {'func': 'cmd_inspect', 'log': 'a.mcap'}),
    'convert': (['convert', 'a.mcap', '-o', 'b.mcap'], {'func': 'cmd_convert', 'log': 'a.mcap', 'output': 'b.mcap'}),
    'score': (['score', 'a.mcap', '-o', 'b.mcap'], {'func': 'cmd_score', 'logs': ['a.mcap'], 'output': 'b.mcap'}),
    'map': (['map', 'a.mcap', '-o', 'm.mcap'], {'func': 'cmd_map', 'log': 'a.mcap', 'output': 'm.mcap'}),
    'batch': (['batch', 'a.mcap', '-o', 'out'],
              {'descriptors': None, 'func': 'cmd_batch', 'logs': ['a.mcap'], 'output': 'out'}),
    'localize': (['localize', 'm.parquet', 'q.mcap', '-o', 'x.parquet'],
                 {'func': 'cmd_localize', 'map': 'm.parquet', 'output': 'x.parquet', 'query': 'q.mcap'}),
    'evaluate': (['evaluate', '--reference', 'r.mcap', '--query', 'q.mcap', '-o', 'out'],
                 {'func': 'cmd_evaluate', 'output': 'out', 'query': 'q.mcap', 'reference': 'r.mcap'}),
    'models': (['models'], {'func': 'cmd_models', 'names': []}),
}


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def _type_name(t: Any) -> str | None:
    return None if t is None else str(getattr(t, "__qualname__", repr(t)))


def _rows(name: str, p: argparse.ArgumentParser) -> set[tuple[Any, ...]]:
    return {(name, tuple(a.option_strings), a.dest, a.default, _type_name(a.type), type(a).__name__, a.nargs, a.const,
             tuple(a.choices) if a.choices is not None else None, a.required)
            for a in p._actions if not isinstance(a, argparse._HelpAction)}


def test_every_flag_parses_to_the_same_dest_type_and_default() -> None:
    subs = _subparsers()
    assert sorted(subs) == sorted({row[0] for row in CONTRACT})
    for name, p in subs.items():
        want = {row for row in CONTRACT if row[0] == name}
        got = _rows(name, p)
        assert got == want, f"{name}: lost {sorted(want - got, key=repr)}; new {sorted(got - want, key=repr)}"


@pytest.mark.parametrize("name", sorted(MINIMAL))
def test_a_minimal_command_line_parses_as_before(name: str) -> None:
    argv, given = MINIMAL[name]
    want = {row[2]: row[3] for row in CONTRACT if row[0] == name and row[3] != argparse.SUPPRESS}
    want.update(command=name, quiet=False, **given)
    got = vars(build_parser().parse_args(argv))
    got["func"] = got["func"].__name__
    assert got == want


def test_fast_and_paper_literal_stay_exclusive(capsys: pytest.CaptureFixture[str]) -> None:
    # shown in different groups (performance, experimental), still one choice of scoring mode
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["map", "a.mcap", "-o", "m.mcap", "--fast", "--paper-literal"])
    assert exc.value.code == 2 and "not allowed with argument --fast" in capsys.readouterr().err


#: Per command: the flags most runs need (within the first 40 lines of --help), the usage line, and the
#: groups, in the order of :data:`memlog.cli.flags.GROUPS`.
LEADS = {
    "map": (["LOG", "-o", "--scores", "--select", "--keep-fraction", "--config", "-q"],
            "usage: memlog map LOG -o OUT.mcap [--keep-fraction F] [options]",
            ["inputs", "outputs", "selection", "scoring", "performance", "experimental"]),
    "localize": (["MAP.parquet", "QUERY_LOG", "-o", "--map", "--annotate", "-k", "-q"],
                 "usage: memlog localize MAP.parquet QUERY_LOG -o MATCHES.parquet",
                 ["inputs", "outputs", "sequence matching", "performance", "experimental"]),
    "evaluate": (["--reference", "--query", "-o", "--truth", "--keep-fraction", "--config", "-q"],
                 "usage: memlog evaluate --reference LOG --query LOG -o OUTDIR",
                 ["inputs", "outputs", "comparisons", "selection", "sequence matching", "scoring", "performance",
                  "experimental"]),
    "score": (["LOG", "-o", "--config", "-q"],
              "usage: memlog score LOG [LOG ...] -o OUT.mcap [options]",
              ["inputs", "outputs", "scoring", "performance", "experimental"]),
    "batch": (["LOG", "-o", "--manifest", "--ray", "--keep-fraction", "--config", "-q"],
              "usage: memlog batch [LOG ...] -o OUTDIR [--ray [ADDRESS]] [options]",
              ["inputs", "outputs", "selection", "scoring", "performance", "experimental"]),
}

#: The flags only experiments and benchmarks use: shown under "experimental", "(experimental)" in their help.
EXPERIMENTAL = {
    "map": {"--dt", "--distinct-weight", "--paper-literal", "--normalize"},
    "batch": {"--dt", "--distinct-weight", "--paper-literal", "--normalize"},
    "score": {"--paper-literal", "--normalize"},
    "localize": {"--time-search"},
    "evaluate": {"--dt", "--distinct-weight", "--paper-literal", "--normalize", "--paper-discarded"},
}


def _flag(a: argparse.Action) -> str:
    return a.option_strings[-1] if a.option_strings else a.dest


def _help(name: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> list[str]:
    monkeypatch.setenv("COLUMNS", "80")  # argparse wraps to the terminal
    with pytest.raises(SystemExit) as exc:
        main([name, "--help"])
    assert exc.value.code == 0
    return capsys.readouterr().out.splitlines()


@pytest.mark.parametrize("name", sorted(LEADS))
def test_help_leads_with_the_common_flags_then_the_groups(name: str, capsys: pytest.CaptureFixture[str],
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    lines = _help(name, capsys, monkeypatch)
    common, usage, groups = LEADS[name]
    assert lines[0] == usage  # compact: not a wall of brackets
    assert "examples:" in lines[:20] and any(line.startswith(f"  memlog {name} ") for line in lines[:20])
    first = lines[:40]
    for flag in common:
        assert any(re.match(rf"  {re.escape(flag)}(?=[ ,]|$)", line) for line in first), (flag, first)
    known = {"examples", "positional arguments", "options", *GROUPS}
    titles = [line[:-1] for line in lines if line[:-1] in known and line.endswith(":")]
    assert titles == ["examples", *(["positional arguments"] if name != "evaluate" else []), "options", *groups]
    assert [t for t in GROUPS if t in groups] == groups  # the one order
    assert max(len(line) for line in lines) <= 80


@pytest.mark.parametrize("name", sorted(EXPERIMENTAL))
def test_experimental_flags_are_marked_and_grouped(name: str) -> None:
    p = _subparsers()[name]
    shown = {g.title: {_flag(a) for a in g._group_actions} for g in p._action_groups}
    assert shown["experimental"] == EXPERIMENTAL[name]
    for a in p._actions:
        assert ("(experimental)" in (a.help or "")) == (_flag(a) in EXPERIMENTAL[name]), _flag(a)
    if name in ("localize", "evaluate"):
        assert "--no-rerank" in shown["sequence matching"] and "--no-hmm" in shown["sequence matching"]
    if name == "evaluate":
        assert "--compare-exact" in shown["comparisons"]


def test_top_level_help_names_the_groups(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COLUMNS", "80")
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    assert "sequence matching, scoring, performance, experimental" in " ".join(capsys.readouterr().out.split())


#: The configs whose settings each command takes from the command line (issue 41: flags are generated from
#: the settings declared on these configs' fields, :mod:`memlog.settings`).
def _configs() -> dict[str, list[type]]:
    from memlog.descriptors.approx import SearchConfig
    from memlog.matching import SequenceConfig
    from memlog.scoring.config import ScoreConfig
    from memlog.selection.config import SelectionConfig
    from memlog.steps.batch import BatchConfig
    from memlog.steps.evaluate import EvaluateConfig
    from memlog.steps.localize import LocalizeConfig
    from memlog.steps.map import MapConfig

    return {"score": [ScoreConfig], "map": [ScoreConfig, SelectionConfig, MapConfig],
            "batch": [ScoreConfig, SelectionConfig, BatchConfig, MapConfig],  # batch's --workers: BatchConfig's
            "localize": [LocalizeConfig, SearchConfig, SequenceConfig],
            "evaluate": [ScoreConfig, SelectionConfig, EvaluateConfig, SequenceConfig]}


#: Each command's flags that are not settings of a config: what is read and written, the config file and
#: preset, the frames' window, and how the run itself behaves.
NOT_SETTINGS = {
    "score": {"-q", "-o", "--config", "--preset", "--max-pixels", "-t", "--start", "--end", "--stride", "--workers"},
    "map": {"-q", "-o", "--config", "--preset", "--max-pixels", "--scores", "--json"},
    "batch": {"-q", "-o", "--config", "--preset", "--max-pixels", "--manifest", "--summary"},
    "localize": {"-q", "-o", "--map", "--annotate", "--query-descriptors", "--json", "--max-pixels", "-t",
                 "--start", "--end", "--stride"},
    "evaluate": {"-q", "-o", "--config", "--preset", "--max-pixels", "--reference", "--query", "--truth", "--start",
                 "--end", "--stride"},
}


#: Settings a command does not take from its command line (`map --maps`: the annotated log's images).
SKIPPED = {"map": {"--maps"}, "batch": {"--maps", "--descriptors"}, "evaluate": {"--maps"}}


@pytest.mark.parametrize("name", sorted(NOT_SETTINGS))
def test_every_setting_flag_comes_from_its_config_field(name: str) -> None:
    from memlog.settings import setting_flags

    declared: dict[str, Any] = {}
    for cls in _configs()[name]:
        for _field, flag in setting_flags(cls):
            declared.setdefault(flag.names[0], flag)
    p = _subparsers()[name]
    seen = set()
    for a in p._actions:
        if isinstance(a, argparse._HelpAction) or not a.option_strings:
            continue
        first = a.option_strings[0]
        seen.add(first)
        if first in NOT_SETTINGS[name]:
            assert first not in declared, f"{name} {first}: declared as a setting, added by hand too"
            continue
        flag = declared.get(first)
        assert flag is not None, f"{name} {first}: not declared on a config field (memlog.settings.setting)"
        assert (a.help, a.dest, tuple(a.option_strings)) == (flag.help, flag.key, flag.names), f"{name} {first}"
    missing = set(declared) - seen - SKIPPED.get(name, set())
    assert not missing, f"{name}: declared settings without a flag: {sorted(missing)}"


def test_the_flags_copy_into_the_configs() -> None:
    """A command line's settings reach the config through the declarations (each flag's value rule)."""
    from memlog.cli.commands import batch_config, evaluate_config, map_config, sequence_config

    parser = build_parser()
    m = map_config(parser.parse_args(["map", "a.mcap", "-o", "m.mcap", "--no-whiten", "--keep-topic", "/gps",
                                      "--descriptor", "none", "--jpeg-quality", "70", "--fast", "--mt", "0.3",
                                      "--keep-fraction", "0.5", "--no-refine"]))
    assert (m.whiten, m.keep_topics, m.descriptor, m.jpeg_quality) == (False, ("/gps",), None, 70)
    assert (m.score.mode, m.score.mt, m.score.fast_refine, m.select.keep_fraction) == ("fast", 0.3, False, 0.5)
    b = batch_config(parser.parse_args(["batch", "a.mcap", "-o", "out", "--ray", "auto", "--workers", "3",
                                        "--no-resume"]))
    assert (b.ray, b.ray_address, b.workers, b.map.workers, b.resume) == (True, "auto", 3, 3, False)
    local = batch_config(parser.parse_args(["batch", "a.mcap", "-o", "out", "--ray"]))
    assert (local.ray, local.ray_address) == (True, None)
    s = sequence_config(parser.parse_args(["localize", "m.parquet", "q.mcap", "-o", "x.parquet", "--keep-stops",
                                           "--no-hmm", "--speeds", "0.5:2"]))
    assert (s.stops, s.hmm, s.rerank, s.speeds) == (False, False, True, (0.5, 2.0))
    e = evaluate_config(parser.parse_args(["evaluate", "--reference", "r.mcap", "--query", "q.mcap", "-o", "o",
                                           "--tolerance", "10", "--no-report", "--sequence", "5"]))
    assert (e.tol_m, e.report, e.sequence.length, e.whiten) == (10.0, False, 5, True)
