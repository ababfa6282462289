"""The Flask test client on a tmp $HOPE_HOME for the run page's API tests (series, provenance,
artifacts): no BrainService, no daemon."""
from __future__ import annotations

import os
from pathlib import Path


class RunPageApp:
    def __init__(self, home: Path):
        from hope_models.settings import load_settings
        from registry.db import Registry
        from webapp import create_app
        from webapp.auth import load_or_create_token

        env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_")}
        env.update({"HOPE_HOME": str(home), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": ""})
        self.settings = load_settings(env=env)
        self.registry = Registry.open(self.settings, migrate=True)
        token = load_or_create_token(self.settings)
        self.app, _ = create_app(self.settings, token=token, registry=self.registry)
        self.client = self.app.test_client()
        self.headers = {"Authorization": f"Bearer {token}"}

    def get(self, path: str, **kw):
        return self.client.get(path, headers=self.headers, **kw)

    def close(self) -> None:
        self.app.extensions["hope"].close()
        self.registry.close()
