"""The planner's HTTP client for the service's REST API (standard library only)."""
from __future__ import annotations

import json
import urllib.error
import urllib.parse
import urllib.request


class ApiError(Exception):
    def __init__(self, status: int, detail: str):
        super().__init__(f"HTTP {status}: {detail}")
        self.status, self.detail = status, detail


class PlannerClient:
    def __init__(self, base_url: str = "http://127.0.0.1:8080", timeout: float = 10.0):
        self.base_url = base_url.rstrip("/")
        self.timeout = timeout

    def get(self, path: str, **params) -> object:
        query = urllib.parse.urlencode({k: v for k, v in params.items() if v is not None})
        url = f"{self.base_url}{path}" + (f"?{query}" if query else "")
        try:
            with urllib.request.urlopen(url, timeout=self.timeout) as r:
                body = r.read()
                ctype = r.headers.get("content-type", "")
        except urllib.error.HTTPError as e:
            try:
                detail = json.loads(e.read()).get("detail", e.reason)
            except (ValueError, AttributeError):
                detail = e.reason
            raise ApiError(e.code, str(detail)) from None
        return json.loads(body) if "json" in ctype else body.decode()

    def health(self) -> dict:
        return self.get("/health")

    def robots(self) -> list[dict]:
        return self.get("/robots")

    def robot(self, robot: str) -> dict:
        return self.get(f"/robots/{urllib.parse.quote(robot)}")

    def sessions(self) -> list[dict]:
        return self.get("/sessions")

    def nodes(self, session_id: int, bbox=None, limit: int = 100, offset: int = 0) -> dict:
        box = ",".join(f"{v:g}" for v in (*bbox[0], *bbox[1])) if bbox else None
        return self.get(f"/sessions/{session_id}/nodes", bbox=box, limit=limit, offset=offset)

    def trajectory(self, session_id: int, format: str = "json"):
        return self.get(f"/sessions/{session_id}/trajectory", format=format)

    def graph(self, session_id: int) -> dict:
        return self.get(f"/sessions/{session_id}/graph")

    def stats(self) -> dict:
        return self.get("/stats")
