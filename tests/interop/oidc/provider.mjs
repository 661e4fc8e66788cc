// An OpenID provider for canlift's single sign-on tests: node-oidc-provider (OpenID Certified),
// over HTTPS with the test PKI's certificate, its development login and consent pages (any
// password is taken), and a company directory: GROUPS_FILE, a JSON object of login names and
// their groups, read at every sign-in (so a test can move someone to another group).
//   node provider.mjs PORT CERT KEY REDIRECT_URI CLIENT_ID CLIENT_SECRET GROUPS_FILE
// Prints "READY <issuer>" once it listens.
import fs from 'node:fs';
import https from 'node:https';
import Provider from 'oidc-provider';

const [port, cert, key, redirect, clientId, clientSecret, groupsFile] = process.argv.slice(2);
const issuer = `https://localhost:${port}`;
const groupsOf = (id) => JSON.parse(fs.readFileSync(groupsFile, 'utf8'))[id] ?? [];

const provider = new Provider(issuer, {
  clients: [{
    client_id: clientId,
    client_secret: clientSecret,
    redirect_uris: [redirect],
    token_endpoint_auth_method: 'client_secret_basic',
  }],
  claims: {
    openid: ['sub'],
    profile: ['preferred_username', 'name'],
    groups: ['groups'],
  },
  async findAccount(ctx, id) {
    return {
      accountId: id,
      async claims() {
        return { sub: id, preferred_username: id, name: id.toUpperCase(), groups: groupsOf(id) };
      },
    };
  },
  pkce: { required: () => true },
  cookies: { keys: ['canlift-test-only-cookie-key'] },
  features: { devInteractions: { enabled: true } },
});

https
  .createServer({ cert: fs.readFileSync(cert), key: fs.readFileSync(key) }, provider.callback())
  .listen(Number(port), '127.0.0.1', () => console.log(`READY ${issuer}`));
