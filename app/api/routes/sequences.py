"""Input sequences: upload (multipart, streamed), list, read, delete."""

from __future__ import annotations

import asyncio
import secrets

from fastapi import APIRouter, HTTPException, Request, Response
from fastapi.concurrency import run_in_threadpool

from app.api.deps import ServiceDep
from app.models import ErrorPublic, SequencePublic, SequencesPublic
from app.services.uploads import UPLOAD_FORMATS, receive_upload

router = APIRouter(prefix="/sequences", tags=["sequences"])

_ACCEPTED = ", ".join(suffix for suffix, _ in UPLOAD_FORMATS)
UPLOAD_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["file"],
                    "properties": {
                        "file": {
                            "type": "string",
                            "format": "binary",
                            "description": f"the sequence: {_ACCEPTED} (a folder of PLY/PCD frames + poses as .zip)",
                        },
                        "frames": {"type": "string", "description": "frame selection start:stop[:step]"},
                        "name": {"type": "string", "maxLength": 200, "description": "display name"},
                    },
                }
            }
        },
    }
}


def _errors(*codes: int) -> dict[int | str, dict[str, object]]:
    return {code: {"model": ErrorPublic} for code in codes}


@router.get("", response_model=SequencesPublic, summary="Uploaded and bundled sequences")
async def list_sequences(service: ServiceDep) -> SequencesPublic:
    data = [SequencePublic.model_validate(s) for s in await run_in_threadpool(service.sequences.list)]
    return SequencesPublic(data=data, count=len(data))


@router.post(
    "",
    status_code=201,
    response_model=SequencePublic,
    summary="Upload a sequence",
    description="Stream a file in any supported format; it is read once to validate it before it is kept. "
    "Uploads are read one at a time; while `max_pending_uploads` are being received or read, one more "
    "gets 429 with a Retry-After header before its body is read.",
    openapi_extra=UPLOAD_BODY,
    responses=_errors(400, 413, 415, 422, 429),
)
async def upload_sequence(request: Request, service: ServiceDep) -> SequencePublic:
    slot = service.sequences.reserve_upload()  # 429 when full, before the body is read
    try:
        upload = await receive_upload(
            request, service.sequences.tmp_dir, secrets.token_hex(8), max_bytes=service.settings.max_upload_bytes
        )
        future = service.sequences.submit_upload(upload, slot)  # the file and the slot are the queue's now
    except BaseException:
        slot.release()
        raise
    # waits on the event loop, holding no thread; a client that goes away leaves the read to finish
    row = await asyncio.shield(asyncio.wrap_future(future))
    return SequencePublic.model_validate(row)


@router.get("/{sequence_id}", response_model=SequencePublic, responses=_errors(404), summary="One sequence")
async def get_sequence(sequence_id: str, service: ServiceDep) -> SequencePublic:
    seq = await run_in_threadpool(service.sequences.get, sequence_id)
    if seq is None:
        raise HTTPException(404, f"sequence {sequence_id!r} not found")
    return SequencePublic.model_validate(seq)


@router.delete(
    "/{sequence_id}",
    status_code=204,
    responses=_errors(404, 409),
    summary="Delete an uploaded sequence",
    description="Bundled samples cannot be deleted, nor sequences with queued or running jobs (409). "
    "Finished jobs keep their results.",
)
def delete_sequence(sequence_id: str, service: ServiceDep) -> Response:
    outcome = service.sequences.delete(sequence_id)
    if outcome == "missing":
        raise HTTPException(404, f"sequence {sequence_id!r} not found")
    if outcome == "bundled":
        raise HTTPException(409, f"{sequence_id!r} is a bundled sample and cannot be deleted")
    if outcome == "busy":
        raise HTTPException(409, f"sequence {sequence_id!r} has queued or running jobs; cancel them first")
    return Response(status_code=204)
