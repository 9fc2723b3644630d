"""The query stages: features, shortlist, matches, poses, sweep, verification, ICP and the
category fit."""
