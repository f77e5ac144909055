"""Accounts: several API keys, each with its owner's name, so that each owner sees only their own
avatars, animations and jobs (``docs/deployment.md``, "Owners").

The keys file (``EVA_API_KEYS_FILE`` or ``eva serve --api-keys-file``), JSON::

    {"accounts": [
        {"owner": "studio-a", "key": "<at least 16 characters>"},
        {"owner": "ops", "key": "<...>", "admin": true}
    ]}

An admin sees and manages everything (records made before accounts existed, too). Without a
keys file the service has one key (``EVA_API_KEY``) or none, and one user who sees everything:
the local mode.
"""

from __future__ import annotations

import hmac
import json
from dataclasses import dataclass
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

# A key is the only thing between the network and every avatar: long enough not to be guessed
# (``openssl rand -hex 24`` gives 48 characters).
MIN_KEY_LENGTH = 16


class Account(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    owner: str = Field(..., pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
    key: str = Field(..., min_length=MIN_KEY_LENGTH, repr=False)
    admin: bool = False


class AccountsFile(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    accounts: tuple[Account, ...] = Field(..., min_length=1)

    @model_validator(mode="after")
    def _unique(self) -> AccountsFile:
        owners = [a.owner for a in self.accounts]
        if len(set(owners)) != len(owners):
            raise ValueError("each owner may appear once")
        if len({a.key for a in self.accounts}) != len(self.accounts):
            raise ValueError("each key may belong to one owner only")
        return self


def read_accounts(path: str | Path) -> tuple[Account, ...]:
    """The accounts in the keys file ``path``; ``ValueError`` saying what is wrong (never a key)."""
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise ValueError(f"cannot read the keys file {path}: {err}") from err
    try:
        return AccountsFile.model_validate(doc).accounts
    except ValidationError as err:  # its own text would quote the values, keys included
        where = "; ".join(f"{'.'.join(map(str, e['loc'])) or '(top)'}: {e['msg']}" for e in err.errors())
        raise ValueError(f"the keys file {path} is not valid: {where}") from None


@dataclass(frozen=True)
class Caller:
    """Who made a request: ``owner`` (None in the local mode, where there are no accounts) and
    whether they see everything (``admin``; always so in the local mode)."""

    owner: str | None
    admin: bool

    def sees(self, account: str | None) -> bool:
        """Whether a record of ``account`` (its owner's name; None: made before accounts) is theirs."""
        return self.admin or (account is not None and account == self.owner)

    @property
    def account(self) -> str | None:
        """The owner name that records made by this caller carry."""
        return self.owner

    @property
    def listed_account(self) -> str | None:
        """Whose records a listing shows them: their own, or everyone's (None) for an admin."""
        return None if self.admin else self.owner


LOCAL = Caller(None, admin=True)


def caller_keys(api_key: str | None, accounts: tuple[Account, ...]) -> tuple[tuple[bytes, Caller], ...]:
    """Each key the service takes, with who sends it: the one key (the local user's), or each
    account's; none without a key."""
    if api_key is not None:
        return ((api_key.encode(), LOCAL),)
    return tuple((a.key.encode(), Caller(a.owner, a.admin)) for a in accounts)


def identify(given: bytes, keys: tuple[tuple[bytes, Caller], ...]) -> Caller | None:
    """Who sends the key ``given`` (the header's bytes) among ``keys``, every key compared in
    constant time; or None."""
    found = None
    for key, caller in keys:  # no early exit: the time does not tell which key was close
        if hmac.compare_digest(given, key):
            found = caller
    return found
