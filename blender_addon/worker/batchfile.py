"""Prompt files and job files for the headless batch (bpy-free). A prompt file has one take per line, read by
mld_core.inputs (the same format and messages as ``python -m mld_core generate --prompts``). A job file is JSON,
``{"jobs": [{"prompt": ..., "seconds": ..., "seed": ..., "keys": ..., "path": ..., "loop": ...} or
{"sequence": [{"prompt": ..., "seconds": ...}, ...]}]}``, with generate's --keys / --path / --sequence formats inline
(docs/control.md). Here: lines and jobs -> validated requests."""

from __future__ import annotations

import json
from pathlib import Path

from mld_core.inputs import InputError as BatchFileError  # noqa: F401 - the batch catches this name
from mld_core.inputs import PromptLine, parse_prompt_lines, read_prompt_file, validate_request  # noqa: F401

SEQUENCE_OVERLAP_S = 0.5  # as generate --sequence: a later segment also makes the previous one's last half second
JOB_KEYS = {"prompt", "seconds", "seed", "keys", "path", "loop", "sequence"}


def requests_from_lines(lines: list[PromptLine], *, default_seconds: float, seed: int, extras: list | None = None,
                        **settings) -> list:
    """Validated requests, one per line; line ``i`` (0-based) uses seed ``seed + i`` (a job's own "seed" wins).

    ``settings`` are passed to :func:`mld_core.inputs.validate_request` (steps, guidance, model_dir, ...);
    ``extras`` (one dict per line, from :func:`read_job_file`) become each request's ``extra``.
    """
    requests = []
    for index, line in enumerate(lines):
        extra = extras[index] if extras else {}
        line_seed = extra.get("seed", seed + index)
        try:
            request = validate_request(line.text, line.seconds(default_seconds), line_seed, **settings)
        except BatchFileError as exc:
            raise BatchFileError(f"line {line.line}: {exc}") from None
        requests.append(request.with_(extra=extra) if extra else request)
    return requests


def read_job_file(path, model_dir=None) -> tuple[list[PromptLine], list[dict]]:
    """(one PromptLine per job: its prompt, or a sequence's first segment; one extra per job: constraints,
    sequence, seed and the job as given, for the manifest)."""
    from mld_core import constraints as C
    from mld_core.inputs import check_seconds, model_limits, whole_number

    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise BatchFileError(f"cannot read job file {path}: {exc.strerror or exc}") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise BatchFileError(f"job file {path} is not valid JSON: {exc}") from None
    jobs = data.get("jobs") if isinstance(data, dict) else None
    if not isinstance(jobs, list) or not jobs:
        raise BatchFileError(f"job file {path}: expected {{\"jobs\": [{{\"prompt\": \"...\"}}, ...]}}")
    limits = model_limits(model_dir)
    lines, extras = [], []
    for n, job in enumerate(jobs, start=1):
        where = f"{path}, job {n}"
        if not isinstance(job, dict) or not (set(job) <= JOB_KEYS) or ("prompt" in job) == ("sequence" in job):
            raise BatchFileError(f"{where}: a job has a \"prompt\" or a \"sequence\" (not both), and only "
                                 f"{', '.join(sorted(JOB_KEYS))}")
        extra = {"job": job, "constraints": C.constraints_from_job(job, where)}
        if "seed" in job:
            extra["seed"] = whole_number(job["seed"], f"{where}: seed")
        if "sequence" in job:
            if extra["constraints"]:
                raise BatchFileError(f"{where}: a sequence takes no keys, path or loop")
            segments = C.sequence_from_data(job["sequence"], f"{where}: sequence")
            for k, (_, seconds) in enumerate(segments):
                check_seconds(seconds + (SEQUENCE_OVERLAP_S if k else 0.0), limits, f"{where}, segment {k + 1}")
            extra["sequence"] = segments
            text, seconds = segments[0]
        else:
            text, seconds = job["prompt"], job.get("seconds")
        frames = None if seconds is None else int(round(float(seconds) * 20))
        lines.append(PromptLine(n, text, frames))
        extras.append(extra)
    return lines, extras
